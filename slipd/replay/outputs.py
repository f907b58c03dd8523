"""slipd's output frames for a merged log (the estimate files: slipd.replay.writers)."""

from __future__ import annotations

import numpy as np

from slipd.codec import N_TX, Codec, kernels
from slipd.codec.tx import fill_tx_rows
from slipd.estimators import registry
from slipd.replay.candump import FLAG_BRS, FLAG_DIRECTION, FLAG_EXTENDED, FLAG_FD, FLAG_TX, Frames


def tx_values(out: np.ndarray, estimator_id: int) -> np.ndarray:
    """Output-frame slots [n, N_TX] from estimator outputs [n, N_OUT] (the daemon's mapping)."""
    values = np.zeros((out.shape[0], N_TX))
    fill_tx_rows(np.ascontiguousarray(out), float(estimator_id), values)
    return values


def output_frames(estimate, channel_index: int, first_counter: int = 0,
                  profile=None) -> Frames:
    """SLIPD_STATE and SLIPD_AUX frames of every tick (what the daemon sends), on the
    profile's output IDs and frame format (slipd.dbc's without a profile)."""
    codec_plan = Codec.output_plan(profile)
    values = tx_values(estimate.out, registry.spec(estimate.method).wire_id)
    n = len(estimate.t)
    parts = []
    for name in ("SLIPD_STATE", "SLIPD_AUX"):
        row = codec_plan.message_rows[name]
        data = np.zeros((n, 8), dtype=np.uint8)
        kernels.encode_rows(codec_plan.plan_i, codec_plan.plan_f, row, values, first_counter,
                            data)
        parts.append((codec_plan.frame_id(name), data))
    t = np.repeat(estimate.t, 2)
    frame_id = np.empty(2 * n, dtype=np.int64)
    data = np.empty((2 * n, 8), dtype=np.uint8)
    for k, (fid, rows) in enumerate(parts):
        frame_id[k::2] = fid
        data[k::2] = rows
    flags = FLAG_DIRECTION | FLAG_TX  # sent by slipd
    flags |= FLAG_FD | FLAG_BRS if codec_plan.is_fd("SLIPD_STATE") else 0
    flags |= FLAG_EXTENDED if codec_plan.is_extended("SLIPD_STATE") else 0
    return Frames(t, frame_id, np.full(2 * n, flags, np.uint8), np.full(2 * n, 8, np.uint8),
                  data, np.full(2 * n, channel_index, np.uint8), [])


def merge(inputs: Frames, outputs: Frames) -> Frames:
    """Input and output frames in time order (outputs after inputs of the same time)."""
    width = max(inputs.data.shape[1], outputs.data.shape[1])
    pad = lambda d: np.pad(d, ((0, 0), (0, width - d.shape[1])))  # noqa: E731
    t = np.concatenate([inputs.t, outputs.t])
    order = np.argsort(np.concatenate([inputs.t, outputs.t + 0.0]), kind="stable")
    return Frames(t[order], np.concatenate([inputs.frame_id, outputs.frame_id])[order],
                  np.concatenate([inputs.flags, outputs.flags])[order],
                  np.concatenate([inputs.dlc, outputs.dlc])[order],
                  np.concatenate([pad(inputs.data), pad(outputs.data)])[order],
                  np.concatenate([inputs.channel, outputs.channel])[order], inputs.channels)
