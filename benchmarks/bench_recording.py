"""Benchmark of the HDF5 recording store (RecordingWriter, RecordingReader).

Writes a synthetic calibration sweep -- per trial a gyro recording (4800, 3) int16 (0.6 s at
8 kHz: smooth joint motion + sensor noise + bias) and eleven small fields (start pose,
timing, the controller's state packets) -- in batches of 512 trials, and reports for each
compression codec: write throughput (MB/s of raw trial data, fsync on, including the final
checkpoint), file size and compression ratio. The same run writes the same data with plain
h5py (file kept open, resize + write per batch, same chunks and codec, no crash safety) and
prints the ratio: what the crash safety costs.

``--crash-study N`` also SIGKILLs writers of the alternatives N times each (SWMR, open-append-
close per batch, keep-open with flush per batch, and RecordingWriter) at random moments and
counts how often the file is left unreadable -- the measurements behind the design choice.

Usage::

    python benchmarks/bench_recording.py                 # 4,000 trials, extrapolated
    python benchmarks/bench_recording.py --trials 33500  # the paper's full sweep
    python benchmarks/bench_recording.py --crash-study 20
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import glob
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator

import h5py
import numpy as np

from timedexec.recording import Field, RecordingReader, RecordingWriter

N_GYRO = 4800  # 0.6 s at 8 kHz
N_STATE = 160  # state packets per trial (about 1.3 s at 8 ms)
FULL_SWEEP = 33_500  # trials per robot in the paper

FIELDS = [
    Field("gyro", (N_GYRO, 3), "int16", unit="LSB", doc="raw gyro, 16.4 LSB per deg/s"),
    Field("joint", (), "int8", doc="actuated joint, 1-based"),
    Field("direction", (), "int8", doc="+1 or -1"),
    Field("q_start_rad", (6,), "float64", unit="rad"),
    Field("t_start_s", (), "float64", unit="s"),
    Field("command_host_time_s", (), "float64", unit="s"),
    Field("gyro_t0_host_s", (), "float64", unit="s"),
    Field("state_host_time_s", (N_STATE,), "float64", unit="s"),
    Field("state_q_rad", (N_STATE, 6), "float32", unit="rad"),
    Field("state_qd_rad_s", (N_STATE, 6), "float32", unit="rad/s"),
    Field("true_actuation_delay_s", (), "float64", unit="s"),
    Field("true_response_delay_s", (), "float64", unit="s"),
]
ROW_BYTES = 8 + sum(f.row_nbytes for f in FIELDS)  # + the trial index


def make_batch(rng: np.random.Generator, trials: np.ndarray) -> dict[str, np.ndarray]:
    """Realistic-looking trial data: smooth rate profiles plus noise, quantised like a MEMS gyro."""
    k = len(trials)
    t = np.arange(N_GYRO) / 8000.0
    onset = rng.uniform(0.02, 0.1, (k, 1))
    peak = rng.uniform(0.2, 1.5, (k, 1)) * rng.choice([-1.0, 1.0], (k, 1))  # rad/s
    s = np.clip((t[None, :] - onset) / 0.15, 0.0, None)
    rate = peak * (s * np.exp(1.0 - s))  # accelerate, decelerate, settle (rad/s)
    axis = rng.normal(size=(k, 1, 3))
    axis /= np.linalg.norm(axis, axis=2, keepdims=True)
    lsb_per_rad_s = 16.4 * 180.0 / np.pi
    gyro = rate[:, :, None] * axis * lsb_per_rad_s
    gyro += rng.normal(0.0, 4.0, gyro.shape) + rng.normal(0.0, 6.0, (k, 1, 3))  # noise, bias
    ts = np.arange(N_STATE) * 0.008
    q0 = rng.uniform(-2.0, 2.0, (k, 6))
    sample = np.minimum((ts * 8000).astype(int), N_GYRO - 1)
    qd = np.zeros((k, N_STATE, 6), dtype=np.float32)
    qd[np.arange(k), :, rng.integers(0, 6, k)] = rate[:, sample]  # the actuated joint moves
    return {
        "trial": trials.astype(np.int64),
        "gyro": np.clip(np.rint(gyro), -32768, 32767).astype(np.int16),
        "joint": rng.choice(np.array([1, 2, 3, 5], dtype=np.int8), k),
        "direction": rng.choice(np.array([-1, 1], dtype=np.int8), k),
        "q_start_rad": q0,
        "t_start_s": trials * 1.9,
        "command_host_time_s": trials * 1.9 + rng.uniform(0, 0.008, k),
        "gyro_t0_host_s": trials * 1.9 - 0.05,
        "state_host_time_s": trials[:, None] * 1.9 + ts + rng.normal(0, 2e-4, (k, N_STATE)),
        "state_q_rad": (q0[:, None, :] + np.cumsum(qd, axis=1) * 0.008).astype(np.float32),
        "state_qd_rad_s": qd + rng.normal(0, 1e-3, qd.shape).astype(np.float32),
        "true_actuation_delay_s": rng.normal(0.02, 0.008, k),
        "true_response_delay_s": rng.normal(0.012, 0.004, k),
    }


def batches(n_trials: int, batch: int, pool: list[dict[str, np.ndarray]]) -> Iterator[dict]:
    """Batches of the sweep; data cycles through a pre-generated pool (generation not timed)."""
    for j, start in enumerate(range(0, n_trials, batch)):
        b = dict(pool[j % len(pool)])
        k = min(batch, n_trials - start)
        b = {name: v[:k] for name, v in b.items()}
        b["trial"] = np.arange(start, start + k, dtype=np.int64)
        yield b


def h5_args(codec: str) -> dict[str, object]:
    if codec == "none":
        return {}
    if codec == "lzf":
        return {"compression": "lzf", "shuffle": True}
    return {"compression": "gzip", "compression_opts": int(codec.split("-")[1]), "shuffle": True}


def write_recording(path: str, codec: str, n: int, batch: int, pool: list) -> float:
    t0 = time.perf_counter()
    with RecordingWriter(path, header={"bench": True}, fields=FIELDS, compression=codec) as w:
        for b in batches(n, batch, pool):
            w.append(b)
    return time.perf_counter() - t0


def write_plain(
    path: str, codec: str, n: int, batch: int, pool: list, fletcher32: bool = True
) -> float:
    """The obvious alternative: one h5py file kept open, no journal, no fsync (with the
    recording's per-chunk Fletcher-32 checksum unless ``fletcher32=False``)."""
    t0 = time.perf_counter()
    with h5py.File(path, "w") as f:
        dsets = {}
        for fld in [Field("trial", (), "int64"), *FIELDS]:
            dsets[fld.name] = f.create_dataset(
                fld.name,
                (0, *fld.shape),
                fld.np_dtype,
                maxshape=(None, *fld.shape),
                chunks=(64, *fld.shape),
                fletcher32=fletcher32,
                **h5_args(codec),
            )
        rows = 0
        for b in batches(n, batch, pool):
            k = len(b["trial"])
            for name, ds in dsets.items():
                ds.resize(rows + k, axis=0)
                ds[rows : rows + k] = b[name]
            rows += k
    return time.perf_counter() - t0


def write_plain_unchecked(path: str, codec: str, n: int, batch: int, pool: list) -> float:
    """Plain h5py without the per-chunk checksum: what the checksum costs."""
    return write_plain(path, codec, n, batch, pool, fletcher32=False)


def read_plain(path: str) -> float:
    t0 = time.perf_counter()
    with h5py.File(path, "r") as f:
        for name in f:
            for a in range(0, f[name].shape[0], 1024):
                f[name][a : a + 1024]
    return time.perf_counter() - t0


def read_all(path: str) -> float:
    t0 = time.perf_counter()
    with RecordingReader(path) as r:
        for _ in r.iter_chunks(1024):
            pass
    return time.perf_counter() - t0


def bench(args: argparse.Namespace) -> None:
    n, batch = args.trials, args.batch
    rng = np.random.default_rng(0)
    pool = [make_batch(rng, np.arange(batch)) for _ in range(4)]
    raw_mb = n * ROW_BYTES / 1e6
    scale = FULL_SWEEP / n
    print(
        f"measured: {n} trials x {len(FIELDS) + 1} fields ({ROW_BYTES / 1e3:.1f} kB raw per "
        f"trial, {raw_mb:.0f} MB raw), batches of {batch}; extrapolated linearly to "
        f"{FULL_SWEEP} trials (x{scale:.2f}); best of {args.repeat} runs"
    )
    work = tempfile.mkdtemp(prefix="bench_recording_", dir=args.dir)
    try:
        print(
            f"{'writer':<26}{'codec':<8}{'write MB/s':>11}{'file MB':>9}{'ratio':>7}"
            f"{'read MB/s':>10}{'full sweep: s':>15}{'GB':>7}"
        )
        results: dict[tuple[str, str], float] = {}
        for codec in args.codecs.split(","):
            for kind, fn in (
                ("RecordingWriter", write_recording),
                ("plain h5py", write_plain),
                ("plain h5py, no checksum", write_plain_unchecked),
            ):
                if kind.startswith("plain h5py") and codec != args.codecs.split(",")[0]:
                    continue
                path = os.path.join(work, f"{kind.split()[0]}_{codec}.h5")
                dt, t_read = np.inf, np.inf
                for _ in range(args.repeat):  # best of N: the machine may be shared
                    for p in glob.glob(path + "*"):
                        os.remove(p)
                    dt = min(dt, fn(path, codec, n, batch, pool))
                    reader = read_all if kind == "RecordingWriter" else read_plain
                    t_read = min(t_read, reader(path))
                size = os.path.getsize(path)
                rd = f"{raw_mb / t_read:10.0f}"
                results[(kind, codec)] = dt
                results[(kind + " read", codec)] = t_read
                print(
                    f"{kind:<26}{codec:<8}{raw_mb / dt:11.0f}{size / 1e6:9.1f}"
                    f"{n * ROW_BYTES / size:7.2f}{rd}{dt * scale:15.1f}{size * scale / 1e9:7.2f}"
                )
                os.remove(path)
        first = args.codecs.split(",")[0]
        ratio = results[("RecordingWriter", first)] / results[("plain h5py", first)]
        print(
            f"crash-safe RecordingWriter / plain h5py write time ({first}): {ratio:.2f}x "
            "(journal with fsync per batch + checkpoints; plain h5py is not crash-safe)"
        )
        w_ck = results[("plain h5py", first)] / results[("plain h5py, no checksum", first)]
        r_ck = (
            results[("plain h5py read", first)] / results[("plain h5py, no checksum read", first)]
        )
        print(
            f"per-chunk Fletcher-32 checksum, plain h5py with / without ({first}): write "
            f"{w_ck:.2f}x, read {r_ck:.2f}x (what detecting a damaged chunk costs)"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------- crash study

STUDY_BATCH = 16


def study_child(mode: str, path: str) -> None:
    """Append forever; row i of every dataset encodes i (checked after the kill)."""
    if mode == "recording":
        w = RecordingWriter(path, header={}, fields=[Field("gyro", (N_GYRO, 3), "int16")])
        print("ready", flush=True)
        n = 0
        while True:
            t = np.arange(n, n + STUDY_BATCH)
            w.append(
                {
                    "trial": t,
                    "gyro": np.broadcast_to(
                        (t % 30000).astype(np.int16)[:, None, None], (STUDY_BATCH, N_GYRO, 3)
                    ),
                }
            )
            n += STUDY_BATCH
    libver = "latest" if mode == "swmr" else None
    f = h5py.File(path, "w", libver=libver)
    f.create_dataset(
        "gyro",
        (0, N_GYRO, 3),
        "int16",
        maxshape=(None, N_GYRO, 3),
        chunks=(STUDY_BATCH, N_GYRO, 3),
        compression="lzf",
    )
    for j in range(10):
        f.create_dataset(
            f"s{j}", (0,), "float64", maxshape=(None,), chunks=(64,), compression="lzf"
        )
    if mode == "swmr":
        f.swmr_mode = True
    if mode == "reopen":
        f.close()
    else:
        f.flush()
    print("ready", flush=True)
    n = 0
    while True:
        if mode == "reopen":
            f = h5py.File(path, "a")
        f["gyro"].resize(n + STUDY_BATCH, axis=0)
        f["gyro"][n:] = (np.arange(n, n + STUDY_BATCH) % 30000).astype(np.int16)[:, None, None]
        for j in range(10):
            f[f"s{j}"].resize(n + STUDY_BATCH, axis=0)
            f[f"s{j}"][n:] = np.arange(n, n + STUDY_BATCH)
        n += STUDY_BATCH
        if mode == "reopen":
            f.close()
        else:
            f.flush()


def _verify(f: h5py.File) -> bool:
    g = f["gyro"]
    ok = np.array_equal(g[:, 0, 0], (np.arange(g.shape[0]) % 30000).astype(np.int16))
    for j in range(10):
        name = f"s{j}"
        if name in f:
            ok &= np.array_equal(f[name][:], np.arange(f[name].shape[0]))
    return bool(ok)


def _clear_status_flags(path: str) -> None:
    """What h5clear -s does, via the library's private property (ctypes)."""
    libdir = os.path.join(os.path.dirname(h5py.__file__), os.pardir, "h5py.libs")
    lib = ctypes.CDLL(glob.glob(os.path.join(libdir, "libhdf5-*"))[0])
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    flag = ctypes.c_bool(True)
    lib.H5Pset(ctypes.c_long(fapl.id), b"clear_status_flags", ctypes.byref(flag))
    h5py.h5f.open(path.encode(), h5py.h5f.ACC_RDWR, fapl).close()


def study_check(mode: str, path: str) -> dict[str, str]:
    out = {}
    if mode == "recording":
        try:
            with RecordingReader(path) as r:
                g = r.read("gyro", slice(None))[:, 0, 0]
                out["RecordingReader"] = (
                    "ok"
                    if np.array_equal(g, (np.arange(len(g)) % 30000).astype(np.int16))
                    else "inconsistent"
                )
        except Exception as exc:
            out["RecordingReader"] = f"ERR {str(exc)[:60]}"
        # resume
        try:
            RecordingWriter(path, resume=True).close()
            out["resume"] = "ok"
        except Exception as exc:
            out["resume"] = f"ERR {str(exc)[:60]}"
    for name, kw in (("h5py 'r'", {}), ("h5py swmr=True", {"swmr": True}), ("h5py 'r+'", {})):
        try:
            with h5py.File(path, "r+" if "r+" in name else "r", **kw) as f:
                out[name] = (
                    "ok" if _verify(f if mode != "recording" else f["trials"]) else ("inconsistent")
                )
        except Exception as exc:
            out[name] = f"ERR {str(exc)[:60]}"
    if mode != "recording" and out["h5py 'r+'"].startswith("ERR"):
        try:
            _clear_status_flags(path)
            with h5py.File(path, "r+") as f:
                out["r+ after clearing flags"] = "ok" if _verify(f) else "inconsistent"
        except Exception as exc:
            out["r+ after clearing flags"] = f"ERR {str(exc)[:60]}"
    return out


def crash_study(n_kills: int, directory: str | None) -> None:
    print(
        f"\ncrash study: {n_kills} SIGKILLs per writer at random moments (seeded) while it "
        f"appends batches of {STUDY_BATCH} trials; what opens afterwards:"
    )
    work = tempfile.mkdtemp(prefix="crash_study_", dir=directory)
    rng = np.random.default_rng(1)
    try:
        for mode in ("swmr", "reopen", "keepopen", "recording"):
            counts: Counter[tuple[str, str]] = Counter()
            errors: Counter[str] = Counter()
            for i in range(n_kills):
                path = os.path.join(work, f"{mode}_{i}.h5")
                proc = subprocess.Popen(
                    [sys.executable, __file__, "--_child", mode, path], stdout=subprocess.PIPE
                )
                assert proc.stdout is not None
                proc.stdout.readline()  # "ready": the file exists, appending starts now
                time.sleep(rng.uniform(0.0, 1.2))
                proc.send_signal(signal.SIGKILL)
                proc.wait()
                proc.stdout.close()
                for check, res in study_check(mode, path).items():
                    counts[(check, res.split()[0])] += 1
                    if res.startswith("ERR"):
                        errors[res] += 1
                for p in glob.glob(path + "*"):
                    with contextlib.suppress(FileNotFoundError):
                        os.remove(p)
            summary = ", ".join(f"{c} {r}: {k}" for (c, r), k in sorted(counts.items()))
            print(f"  {mode:<10} {summary}")
            for e, k in errors.most_common(3):
                print(f"  {'':<10} {k}x {e}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=4000, help="trials to write (default 4000)")
    p.add_argument("--batch", type=int, default=512, help="trials per append (default 512)")
    p.add_argument(
        "--codecs",
        default="lzf,gzip-1,none",
        help="comma-separated codecs; the first is also written with plain h5py",
    )
    p.add_argument("--repeat", type=int, default=3, help="runs per case, best kept (3)")
    p.add_argument("--dir", default=None, help="directory for the files (default: temp dir)")
    p.add_argument(
        "--crash-study",
        type=int,
        default=0,
        metavar="N",
        help="also SIGKILL each alternative writer N times",
    )
    p.add_argument("--_child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._child:
        study_child(*args._child)
        return 0
    bench(args)
    if args.crash_study:
        crash_study(args.crash_study, args.dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
