"""The codec: DBC + profile -> compiled plan -> numba decode/encode kernels.

:class:`Codec` owns the plans and the decode-side state (latch, counters, error counts) of
one bus. The daemon feeds it frame by frame (:meth:`Codec.decode`); the batch engine hands
the same arrays to :func:`slipd.codec.kernels.latch_ticks`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slipd.channels import N_IN, In
from slipd.codec import kernels
from slipd.codec.calibration import calibration_vector
from slipd.codec.kernels import ERROR_NAMES, N_ERR
from slipd.codec.plan import (
    N_TX,
    Plan,
    Tx,
    channel_timeouts,
    compile_input_plan,
    compile_output_plan,
)
from slipd.errors import CodecError
from slipd.profile import Profile, load_profile

__all__ = ["Codec", "DecodeState", "Tx", "N_TX", "ERROR_NAMES"]


@dataclass
class DecodeState:
    """Mutable decode-side state: the latch and the per-message bookkeeping."""

    latch: np.ndarray
    msg_state: np.ndarray
    errors: np.ndarray
    scratch: np.ndarray = field(default_factory=lambda: np.zeros(N_IN))

    @classmethod
    def new(cls, n_messages: int) -> DecodeState:
        latch = np.zeros((3, N_IN), dtype=np.float64)
        latch[kernels.LATCH_TIME] = -np.inf
        msg_state = np.zeros((n_messages, 2), dtype=np.float64)
        msg_state[:, 0] = -1.0
        msg_state[:, 1] = -np.inf
        errors = np.zeros((n_messages + 1, N_ERR), dtype=np.int64)
        return cls(latch, msg_state, errors)


class Codec:
    """Decode a profile's input frames and encode slipd's output frames."""

    def __init__(self, profile: Profile):
        self.profile = profile
        self.inputs: Plan = compile_input_plan(profile)
        self.outputs: Plan = compile_output_plan(outputs=profile.outputs)
        self.channel_timeouts = channel_timeouts(profile)
        #: the profile's [calibration] in the sampling kernel's form (slipd.codec.calibration)
        self.calibration = calibration_vector(profile.calibration)
        self.state = DecodeState.new(self.inputs.n_messages)
        self._tx_counters = dict.fromkeys(self.outputs.message_names, 0)
        self._input_counters = dict.fromkeys(self.inputs.message_names, 0)

    @staticmethod
    def output_plan(profile: Profile | None = None) -> Plan:
        """The encode plan of slipd's output frames: slipd.dbc's layout with the profile's
        output IDs, bus and frame format (slipd.dbc's IDs without a profile)."""
        return compile_output_plan(outputs=profile.outputs if profile is not None else None)

    def bus_index(self, name: str) -> int:
        """Index of bus ``name`` in the profile's bus order (what decode's ``bus`` takes)."""
        try:
            return self.inputs.buses.index(name)
        except ValueError:
            raise CodecError(f"profile {self.profile.name} has no bus {name!r}; its buses: "
                             f"{list(self.inputs.buses)}") from None

    @classmethod
    def from_profile(cls, profile: Profile | str = "default") -> Codec:
        return cls(load_profile(profile) if isinstance(profile, str) else profile)

    # ---- decode -------------------------------------------------------------------------
    def decode(self, frame_id: int, data: bytes | np.ndarray, t: float,
               extended: bool = False, state: DecodeState | None = None, bus: int = 0) -> int:
        """Decode one frame received on bus index ``bus`` into the latch (or into ``state``,
        a scratch one); returns the message row, -1 unknown, -2 rejected."""
        payload = np.frombuffer(bytes(data), dtype=np.uint8) if not isinstance(
            data, np.ndarray) else data
        p = self.inputs
        s = self.state if state is None else state
        return kernels.decode_frame(p.plan_i, p.plan_f, p.lookup, bus, frame_id, extended,
                                    len(payload), payload, t, p.timeouts, s.latch,
                                    s.msg_state, s.errors, s.scratch)

    def sample(self, t: float, u: np.ndarray) -> np.ndarray:
        """Sample-and-hold of the latch at tick time ``t`` into ``u`` (see channels.U_LEN)."""
        kernels.sample_latch(self.state.latch, self.channel_timeouts, self.calibration, t, u)
        return u

    def error_counts(self) -> dict[str, dict[str, int]]:
        """Per-message counters by name (and ``unknown`` for frames of unknown IDs)."""
        result = {}
        for row, name in enumerate(self.inputs.message_names):
            counts = zip(ERROR_NAMES, self.state.errors[row], strict=True)
            result[name] = {k: int(v) for k, v in counts}
        result["unknown"] = {"unknown_id": int(self.state.errors[-1, kernels.ERR_UNKNOWN_ID])}
        return result

    def rejected_total(self) -> int:
        errors = self.state.errors
        return int(errors[:, kernels.ERR_LENGTH:kernels.ERR_UNKNOWN_ID].sum())

    # ---- encode -------------------------------------------------------------------------
    def encode_channels(self, message: str, values: dict[In, np.ndarray],
                        first_counter: int | None = None) -> tuple[int, np.ndarray]:
        """Encode input message ``message`` once per sample (simulation, import).

        ``values`` maps each channel of the message to an array of SI values (all the same
        length). Returns the frame ID and uint8 [n, dlc] payloads with counters and CRCs;
        counters continue across calls unless ``first_counter`` is given.
        """
        plan = self.inputs
        if message not in plan.message_rows:
            raise CodecError(f"message {message!r} is not an input of profile "
                             f"{self.profile.name}; inputs: {list(plan.message_names)}")
        mmap = self.profile.messages[message]
        missing = [c.name.lower() for c in mmap.channels if c not in values]
        if missing:
            raise CodecError(f"encode {message}: no values for channel(s) {missing}")
        lengths = {len(np.atleast_1d(v)) for v in values.values()}
        if len(lengths) != 1:
            raise CodecError(f"encode {message}: channel arrays differ in length {lengths}")
        n = lengths.pop()
        slots = np.zeros((n, N_IN), dtype=np.float64)
        for channel, array in values.items():
            slots[:, channel] = np.asarray(array, dtype=np.float64)
        row = plan.message_rows[message]
        out = np.zeros((n, plan.dlc(message)), dtype=np.uint8)
        counter = self._input_counters[message] if first_counter is None else first_counter
        kernels.encode_rows(plan.plan_i, plan.plan_f, row, slots, counter, out)
        self._input_counters[message] = counter + n
        return plan.frame_id(message), out

    def encode_output(self, message: str, values: np.ndarray, out: np.ndarray,
                      advance_counter: bool = True) -> int:
        """Encode one output frame (SLIPD_STATE/AUX/DIAG) from ``values`` [N_TX] into ``out``.

        Returns the frame ID. The alive counter advances with every call unless
        ``advance_counter`` is False (the daemon's dry runs, whose frames are never sent).
        """
        plan = self.outputs
        row = plan.message_rows[message]
        counter = self._tx_counters[message]
        kernels.encode_frame(plan.plan_i, plan.plan_f, row, values, counter, out)
        if advance_counter:
            self._tx_counters[message] = (counter + 1) % 16
        return plan.frame_id(message)
