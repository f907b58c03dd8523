"""Batch decode throughput of the compiled codec against a cantools decode_message loop.

Frames: every input message of the default profile at its rate, encoded with valid counters
and CRCs (what the car's bus carries). Both paths decode the same frames; the codec also
checks CRC/counter and latches, which cantools does not.

    .venv/bin/python -m benchmarks.codec [--seconds-of-bus 600]
"""

from __future__ import annotations

import argparse
import time

import cantools
import numpy as np

from slipd.channels import U_LEN
from slipd.codec import Codec, DecodeState, kernels
from slipd.profile import load_profile


def bus_frames(codec: Codec, seconds: float, rng: np.random.Generator):
    ids, rows, times = [], [], []
    for name, mmap in codec.profile.messages.items():
        n = int(seconds * mmap.rate_hz)
        values = {c: rng.normal(0.0, 1.0, n) + (10.0 if "WHEEL" in c.name else 0.0)
                  for c in mmap.channels}
        frame_id, data = codec.encode_channels(name, values)
        ids.append(np.full(n, frame_id))
        rows.append(data)
        times.append(np.arange(n) / mmap.rate_hz + rng.uniform(0, 1e-3))
    t = np.concatenate(times)
    order = np.argsort(t, kind="stable")
    return t[order], np.concatenate(ids)[order].astype(np.int64), np.concatenate(rows)[order]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds-of-bus", type=float, default=600.0)
    parser.add_argument("--cantools-frames", type=int, default=50_000)
    args = parser.parse_args()
    profile = load_profile("default")
    codec = Codec(profile)
    t, ids, data = bus_frames(codec, args.seconds_of_bus, np.random.default_rng(0))
    n = len(t)
    flags = np.zeros(n, np.uint8)
    dlc = np.full(n, 8, np.int64)
    p = codec.inputs

    def decode_all() -> float:
        state = DecodeState.new(p.n_messages)
        U = np.zeros((1, U_LEN))
        started = time.perf_counter()
        kernels.latch_ticks(p.plan_i, p.plan_f, p.lookup, p.timeouts, codec.channel_timeouts,
                            codec.calibration, t, np.zeros(n, np.int64), ids, flags, dlc,
                            data, np.array([t[-1]]), np.array([n], np.int64), state.latch,
                            state.msg_state,
                            state.errors, state.scratch, U)
        elapsed = time.perf_counter() - started
        assert state.errors[:, kernels.ERR_ACCEPTED].sum() == n, "every frame must pass"
        return elapsed

    decode_all()  # compile / load the cache
    fast = min(decode_all() for _ in range(5))
    db = cantools.database.load_file(str(profile.dbc_path))
    m = min(args.cantools_frames, n)
    payloads = [bytes(row) for row in data[:m]]
    started = time.perf_counter()
    for frame_id, payload in zip(ids[:m].tolist(), payloads, strict=True):
        db.decode_message(frame_id, payload)
    slow = time.perf_counter() - started
    fast_rate, slow_rate = n / fast, m / slow
    print(f"frames: {n} ({args.seconds_of_bus:.0f} s of the default profile's bus)")
    print(f"slipd codec batch decode (CRC, counter, range, latch): {fast_rate / 1e6:8.2f} M "
          "frames/s")
    print(f"cantools decode_message loop ({m} frames):             {slow_rate / 1e6:8.3f} M "
          "frames/s")
    print(f"ratio: {fast_rate / slow_rate:.0f}x")


if __name__ == "__main__":
    main()
