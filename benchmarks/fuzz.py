"""Fuzzing at scale: corrupted frames through the codec and every estimator, malformed lines
through the candump reader, garbage datagrams through slipd_unix. Prints counts, crashes
(any exception but the documented LogFormatError) and broken promises (a VALID tick whose
beta, beta rate, vx or vy is not finite; a frame no bus can carry read from a log); all
must be 0.

    .venv/bin/python -m benchmarks.fuzz                      # 1e6 frames, 1e5 lines
    .venv/bin/python -m benchmarks.fuzz --frames 1e5 --lines 1e4 --seed 3

Frames start from a simulated drive encoded through the default profile (valid CRCs and
counters), then are mutated: bit flips, truncation and padding, IDs moved onto other input
messages, timestamps shuffled, repeated or frozen; a share is left intact so the estimators
see real dynamics between the faults. Lines start from the same drive's candump text and get
character insertions, deletions and substitutions drawn from the alphabet lines are made of.
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

ALPHABET = b"()#. RTrt0123456789ABCDEFabcdefxX-\t\r\n"


def drive_frames(seconds: float, seed: int):
    from slipd.profile import load_profile
    from slipd.sim import simulate
    from slipd.sim.writer import encode_frames

    profile = load_profile("default")
    t, ids, data, dlc = encode_frames(simulate("handling_high_mu", duration=seconds,
                                               seed=seed), profile, epoch=1.7e9)
    return profile, t, ids, data, dlc


def mutate_frames(n: int, seed: int, base):
    """n frames: copies of the drive's frames (cycled), two thirds of them corrupted."""
    _, t, ids, data, dlc = base
    rng = np.random.default_rng(seed)
    index = np.arange(n) % len(t)
    cycle = np.arange(n) // len(t)
    span = t[-1] - t[0] + 0.01
    out_t = t[index] + cycle * span
    out_id = ids[index].copy()
    out_data = np.zeros((n, 64), dtype=np.uint8)
    out_data[:, :8] = data[index]
    out_dlc = dlc[index].astype(np.int64)
    kind = rng.integers(0, 9, n)
    flips = kind == 1  # bit flips in the payload (CRC, counter, signals)
    rows = np.flatnonzero(flips)
    out_data[rows, rng.integers(0, 8, len(rows))] ^= (1 << rng.integers(0, 8, len(rows))
                                                      ).astype(np.uint8)
    out_dlc[kind == 2] = rng.integers(0, 65, int(np.sum(kind == 2)))  # wrong lengths
    rows = np.flatnonzero(kind == 3)  # random payloads, random lengths
    out_data[rows] = rng.integers(0, 256, (len(rows), 64), dtype=np.uint8)
    out_dlc[rows] = rng.integers(0, 65, len(rows))
    unique_ids = np.unique(ids)
    rows = np.flatnonzero(kind == 4)  # onto another input message's ID
    out_id[rows] = rng.choice(unique_ids, len(rows))
    rows = np.flatnonzero(kind == 5)  # random IDs
    out_id[rows] = rng.integers(0, 0x800, len(rows))
    rows = np.flatnonzero(kind == 6)  # the previous frame again (a repeat / stuck sender)
    rows = rows[rows > 0]
    out_data[rows] = out_data[rows - 1]
    out_id[rows] = out_id[rows - 1]
    out_dlc[rows] = out_dlc[rows - 1]
    rows = np.flatnonzero(kind == 7)  # timestamps jittered (never backwards: see below)
    out_t[rows] += rng.uniform(0, 0.005, len(rows))
    out_t = np.maximum.accumulate(out_t)  # the time axis a log must have (checked apart)
    return out_t, out_id, out_dlc, out_data


def fuzz_codec(frames, profile) -> dict:
    """Each frame through Codec.decode, as the daemon calls it per received frame."""
    from slipd.codec import Codec

    codec = Codec(profile)
    t, ids, dlc, data = frames
    crashes, results = 0, {}
    first = ""
    started = time.perf_counter()
    for k in range(len(t)):
        try:
            r = codec.decode(int(ids[k]), data[k, :dlc[k]], float(t[k]))
            results[min(r, 0)] = results.get(min(r, 0), 0) + 1
        except Exception:  # noqa: BLE001 - a crash is what is counted here
            crashes += 1
            first = first or traceback.format_exc(limit=3)
    return {"frames": len(t), "crashes": crashes, "accepted": results.get(0, 0),
            "rejected": results.get(-2, 0), "unknown": results.get(-1, 0),
            "seconds": time.perf_counter() - started, "first_crash": first,
            "errors": codec.error_counts()}


#: what a VALID status vouches for (slipd.estimators.supervision.supervise); mu and sigma
#: may be NaN for "not estimated" (zero has no sigma, most methods no mu on these inputs)
PROMISED = ("BETA", "BETA_RATE", "VX", "VY")


def fuzz_estimators(frames, profile, methods: list[str]) -> list[dict]:
    """The whole log through the batch engine and every estimator: a VALID tick must have
    finite values where VALID vouches for them (PROMISED)."""
    from slipd.channels import ST_VALID, Out
    from slipd.replay.candump import Frames
    from slipd.replay.engine import latch_log, run_method

    t, ids, dlc, data = frames
    log = Frames(t, ids.astype(np.int64), np.zeros(len(t), np.uint8),
                 np.minimum(dlc, 64).astype(np.uint8), data, np.zeros(len(t), np.uint8),
                 ["can0"], "fuzz")
    inputs = latch_log(log, profile)
    rows = []
    for name in methods:
        started = time.perf_counter()
        try:
            out = run_method(inputs, profile, name).out
            valid = (out[:, Out.STATUS].astype(np.int64) & ST_VALID) != 0
            promised = out[:, [getattr(Out, name) for name in PROMISED]]
            broken = int(np.sum(valid & ~np.all(np.isfinite(promised), axis=1)))
            rows.append({"method": name, "ticks": len(out), "valid": int(valid.sum()),
                         "valid_not_finite": broken, "crash": "",
                         "seconds": time.perf_counter() - started})
        except Exception as exc:  # noqa: BLE001
            rows.append({"method": name, "ticks": 0, "valid": 0, "valid_not_finite": 0,
                         "crash": f"{type(exc).__name__}: {exc}",
                         "seconds": time.perf_counter() - started})
    return rows


def malformed_lines(n: int, seed: int, base, workdir: Path) -> Path:
    from slipd.replay.candump import write_candump

    _, t, ids, data, dlc = base
    clean = workdir / "clean.log"
    write_candump(clean, t, ids, data, dlc=dlc)
    lines = clean.read_bytes().splitlines()
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        line = bytearray(lines[k % len(lines)])
        for _ in range(int(rng.integers(1, 4))):
            action, at = rng.integers(0, 3), int(rng.integers(0, len(line) + 1))
            char = ALPHABET[int(rng.integers(0, len(ALPHABET)))]
            if action == 0:
                line.insert(at, char)
            elif action == 1 and line:
                del line[min(at, len(line) - 1)]
            elif line:
                line[min(at, len(line) - 1)] = char
        out.append(bytes(line).replace(b"\n", b" "))
    path = workdir / "malformed.log"
    path.write_bytes(b"\n".join(out) + b"\n")
    return path


def fuzz_reader(path: Path) -> dict:
    """The malformed file with --skip-bad, and each line alone without it."""
    from slipd.errors import LogFormatError
    from slipd.replay.candump import FLAG_ERROR, FLAG_FD, read_candump

    crashes, impossible, first = 0, 0, ""
    started = time.perf_counter()
    try:
        frames = read_candump(path, skip_bad=True)
        for k in range(len(frames)):
            flags, length = int(frames.flags[k]), int(frames.dlc[k])
            if flags & FLAG_ERROR:
                continue
            if (not flags & FLAG_FD and length > 8) or frames.frame_id[k] > 0x1FFFFFFF or (
                    not flags & 1 and frames.frame_id[k] > 0x7FF):
                impossible += 1
        kept, bad = len(frames), frames.bad_lines
    except Exception:  # noqa: BLE001
        crashes += 1
        first = traceback.format_exc(limit=3)
        kept = bad = 0
    skip_seconds = time.perf_counter() - started
    lines = path.read_bytes().splitlines()
    sample = lines[:: max(1, len(lines) // 2000)]  # one line per file: the strict path
    single = path.with_name("one.log")
    strict_errors = 0
    for line in sample:
        single.write_bytes(line + b"\n")
        try:
            read_candump(single)
        except LogFormatError as exc:
            strict_errors += 1
            if str(single) not in str(exc):
                crashes += 1
        except Exception:  # noqa: BLE001
            crashes += 1
            first = first or traceback.format_exc(limit=3)
    return {"lines": len(lines), "kept": kept, "bad": bad, "impossible": impossible,
            "crashes": crashes, "first_crash": first, "seconds": skip_seconds,
            "strict_sample": len(sample), "strict_errors": strict_errors}


def fuzz_datagrams(n: int, seed: int, workdir: Path) -> dict:
    """Random datagrams (random sizes, random bytes) into a slipd_unix participant."""
    import can

    rng = np.random.default_rng(seed)
    bus = can.Bus(interface="slipd_unix", channel=str(workdir / "bus"))
    sender = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sender.settimeout(5.0)  # a receiver that stopped reading would block a plain send
    crashes, frames, first = 0, 0, ""
    try:
        for k in range(n):
            size = int(rng.choice([0, 1, 5, 15, 16, 17, 71, 72, 73, 200]))
            sender.sendto(rng.integers(0, 256, size, dtype=np.uint8).tobytes(), str(bus.path))
            if k % 8 == 7 or k == n - 1:
                while True:
                    try:
                        message = bus.recv(0.0)
                    except Exception:  # noqa: BLE001
                        crashes += 1
                        first = first or traceback.format_exc(limit=3)
                        break
                    if message is None:
                        break
                    frames += 1
        malformed = bus.malformed
    finally:
        sender.close()
        bus.shutdown()
    return {"datagrams": n, "frames": frames, "malformed": malformed, "crashes": crashes,
            "first_crash": first}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=float, default=1e6)
    parser.add_argument("--lines", type=float, default=1e5)
    parser.add_argument("--datagrams", type=float, default=1e5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", default="all", help="estimators for the batch pass")
    args = parser.parse_args()
    from slipd.estimators.registry import parse_names

    methods = parse_names(args.methods)
    drive = drive_frames(120.0, args.seed)
    frames = mutate_frames(int(args.frames), args.seed, drive)
    workdir = Path(tempfile.mkdtemp(prefix="slipd-fuzz-"))
    print(f"fuzz: seed {args.seed}, {len(frames[0]):,} frames (2/3 corrupted) from a "
          f"simulated drive, {int(args.lines):,} malformed lines, {int(args.datagrams):,} "
          f"datagrams; {os.cpu_count()} CPUs")
    codec = fuzz_codec(frames, drive[0])
    print(f"codec: {codec['frames']:,} frames in {codec['seconds']:.1f} s "
          f"({codec['frames'] / codec['seconds'] / 1e3:.0f} k/s): accepted {codec['accepted']:,}"
          f", rejected {codec['rejected']:,}, unknown ID {codec['unknown']:,}; crashes "
          f"{codec['crashes']}")
    for name, counts in codec["errors"].items():
        print(f"  {name}: {counts}")
    if codec["first_crash"]:
        print(codec["first_crash"])
    rows = fuzz_estimators(frames, drive[0], methods)
    broken = sum(r["valid_not_finite"] for r in rows)
    crashed = [r for r in rows if r["crash"]]
    print(f"estimators (batch engine, {rows[0]['ticks'] if rows else 0:,} ticks each): "
          f"{len(rows)} methods, VALID but not finite {broken}, crashes {len(crashed)}")
    for r in rows:
        print(f"  {r['method']:<24} valid {r['valid'] / max(r['ticks'], 1) * 100:5.1f} % "
              f"of ticks, valid-not-finite {r['valid_not_finite']}, {r['seconds']:.1f} s"
              + (f"  CRASH {r['crash']}" if r["crash"] else ""))
    reader = fuzz_reader(malformed_lines(int(args.lines), args.seed, drive, workdir))
    print(f"candump reader: {reader['lines']:,} mutated lines, --skip-bad in "
          f"{reader['seconds']:.2f} s: {reader['kept']:,} read, {reader['bad']:,} skipped, "
          f"impossible frames read {reader['impossible']}; {reader['strict_sample']:,} "
          f"lines alone without it: {reader['strict_errors']:,} LogFormatErrors; crashes "
          f"{reader['crashes']}")
    if reader["first_crash"]:
        print(reader["first_crash"])
    grams = fuzz_datagrams(int(args.datagrams), args.seed, workdir)
    print(f"slipd_unix: {grams['datagrams']:,} random datagrams: {grams['frames']:,} read as "
          f"frames, {grams['malformed']:,} dropped as malformed; crashes {grams['crashes']}")
    if grams["first_crash"]:
        print(grams["first_crash"])
    total = codec["crashes"] + len(crashed) + reader["crashes"] + grams["crashes"]
    promises = broken + reader["impossible"]
    print(f"total: crashes {total}, broken promises {promises} "
          f"({'ok' if total == promises == 0 else 'FAILED'})")


if __name__ == "__main__":
    main()
