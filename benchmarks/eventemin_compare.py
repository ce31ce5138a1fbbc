"""cmax-taichi against EventEMin (Nunes & Demiris, ECCV 2020 / TPAMI 2021) on the same events.

Usage::

    python -m benchmarks.eventemin_compare --eventemin /work/peers/EventEMin [--data ../shared/data]
        [--out eventemin-results] [--repeats 3]

``--eventemin`` is a checkout of github.com/ImperialCollegeLondon/EventEMin built with
``cmake .. -DEventEMin_BATCH_MODE=ON -DEventEMin_INCREMENTAL_MODE=ON && make`` (it needs Eigen, GSL and
OpenCV; Eigen 3.4 needs an ``isfinite`` overload for ``AutoDiffScalar``). Its code is not part of this
project: without the built examples the comparison is skipped with a message.

Recordings: the ECD poster_rotation cut of the shared data (``--data``; its ``motion.txt`` holds the
IMU gyro at the middle of the cut) and EventEMin's own samples ``dataset/poster_rotation`` and
``dataset/poster_6dof`` (no ground truth ships with them). For each, a temporary folder holds the
events and the calibration in EventEMin's format (``calib.txt`` with the sensor size on a second line).

* **Batch**: EventEMin's ``example_test_sequence DIR N`` (rotation model, approximate Tsallis dispersion,
  GSL conjugate gradient from 1e-6, its defaults) with ``N`` the events that stay on the sensor after
  its undistortion, i.e. one batch of all of them; against ``maximize()`` with its defaults on
  ``ContrastMaximization(events, "rotation3", camera)`` (the same recording; undistorted by the
  problem). Times: EventEMin's whole process (reading the text file, its undistortion map and the solve),
  our ``maximize()`` call alone (the problem built and its kernels loaded beforehand), and our problem
  set-up plus ``maximize()``.
* **Sliding windows**: EventEMin's incremental mode ``example_incremental_test_sequence DIR 5000``
  (rotation, incremental potential, 5,000 most recent events, an estimate per 5,000 events) against
  ``sequence.process(recording, "rotation3", n_events=5000)`` (5,000-event windows, warm-started).
  Events per second of wall time and of CPU time (all threads; both programs use the two cores).

Estimates are compared with the gyro where there is one: EventEMin's batch estimates mapped to the
gyro's frame as ``(w1, -w2, w3)``, as its ``dataset/poster_rotation/sequence_error.m`` does, its
incremental ones as they are (their ``w_y`` has the gyro's sign). Writes ``eventemin_compare.csv`` and
``eventemin_compare.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

BATCH_EXE = "example_test_sequence"
INCREMENTAL_EXE = "example_incremental_test_sequence"
WINDOW = 5000


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _self_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def eventemin_folder(source: Path, folder: Path, width: int, height: int) -> Path:
    """``folder`` with ``source``'s events and its calibration in EventEMin's format.

    The events are copied without the file's trailing whitespace (its final newline, a ``\\r`` of a
    Windows line end): EventEMin's readers loop ``while (!fin.eof())``, so after the last line they
    read once more from an exhausted stream, into an uninitialised event whose pixel then indexes the
    undistortion map (``event/io.h``): a SIGSEGV or not, by chance (its incremental example died so on
    the shared poster_rotation cut)."""
    folder.mkdir(parents=True)
    text = (source / "events.txt").read_text()
    (folder / "events.txt").write_text(text.rstrip())
    lines = [ln for ln in (source / "calib.txt").read_text().splitlines() if ln.strip()]
    if len(lines) == 1:
        lines.append(f"{width} {height}")
    (folder / "calib.txt").write_text("\n".join(lines[:2]) + "\n")
    return folder


def kept_by_eventemin(events, camera) -> int:
    """Events that EventEMin's undistortion keeps: the undistorted position of the event's pixel,
    rounded, inside the sensor (``event/io.h``)."""
    W, H = events.sensor_size
    ux, uy = camera.undistort_points(np.round(events.x), np.round(events.y))
    with np.errstate(invalid="ignore"):
        x, y = np.round(ux), np.round(uy)
    return int(np.count_nonzero((x >= 0) & (x < W) & (y >= 0) & (y < H)))


def run_timed(cmd: list[str]) -> tuple[float, float, str]:
    """``(wall s, CPU s of the child, stdout)``."""
    c0, t0 = _children_cpu(), time.perf_counter()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return time.perf_counter() - t0, _children_cpu() - c0, out


def read_estimates(path: Path) -> np.ndarray:
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def eventemin_batch(exe: Path, folder: Path, n_kept: int, out: Path) -> tuple[float, float, np.ndarray, int]:
    """EventEMin's batch solve of one batch of (about) all events: ``(wall, cpu, estimate, N)``.

    Its reader refuses a batch short of ``N`` events, so ``N`` steps down by 0.2% until it runs (the
    two undistortions round a few border events differently)."""
    n = n_kept
    for _ in range(20):
        name = f"batch{n}"
        wall, cpu, _ = run_timed([str(exe), str(folder), str(n), str(out), name])
        est = read_estimates(out / f"{name}_estimates.txt")
        if len(est):
            return wall, cpu, est[-1, 1:], n
        n = int(n * 0.998)
    raise RuntimeError(f"EventEMin's batch example gave no estimate on {folder}")


def compare(recording: Path, label: str, exe_dir: Path, tmp: Path, repeats: int, gyro) -> dict:
    """One recording: EventEMin's batch and incremental runs and ours, timed (medians of ``repeats``)."""
    import cmax_taichi as cm
    from cmax_taichi import io, metrics
    from cmax_taichi.solve.sequence import process

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with io.open_recording(recording) as rec:
            events, camera = rec.read(), rec.camera
    W, H = events.sensor_size
    folder = eventemin_folder(recording, tmp / "events", W, H)
    out = tmp / "estimates"
    out.mkdir()
    n_kept = kept_by_eventemin(events, camera)
    row: dict = {"recording": label, "events": len(events)}

    # --- batch ---
    ee_walls, ee_cpus = [], []
    for _ in range(repeats):
        wall, cpu, ee_est, n_used = eventemin_batch(exe_dir / BATCH_EXE, folder, n_kept, out)
        ee_walls.append(wall)
        ee_cpus.append(cpu)
    ee_gyro = ee_est * np.array([1.0, -1.0, 1.0])
    walls, cpus, setups = [], [], []
    for _ in range(repeats):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0, c0 = time.perf_counter(), _self_cpu()
            prob = cm.ContrastMaximization(events, warp="rotation3", camera=camera)
            t1, c1 = time.perf_counter(), _self_cpu()
            res = cm.maximize(prob)
            t2, c2 = time.perf_counter(), _self_cpu()
        walls.append(t2 - t1)
        cpus.append(c2 - c1)
        setups.append(t2 - t0)
    row.update(
        eventemin_batch_events=n_used,
        eventemin_batch_wall_s=statistics.median(ee_walls),
        eventemin_batch_cpu_s=statistics.median(ee_cpus),
        eventemin_batch_theta=np.round(ee_gyro, 4).tolist(),
        ours_events=prob.n_events,
        ours_maximize_wall_s=statistics.median(walls),
        ours_maximize_cpu_s=statistics.median(cpus),
        ours_setup_and_maximize_wall_s=statistics.median(setups),
        ours_evaluations=res.n_evaluations,
        ours_theta=np.round(res.theta, 4).tolist(),
    )
    if gyro is not None:
        row["eventemin_batch_error"] = float(metrics.angular_velocity_error(ee_gyro, gyro)["relative"][0])
        row["ours_batch_error"] = float(metrics.angular_velocity_error(res.theta, gyro)["relative"][0])

    # --- sliding windows / incremental ---
    inc_walls, inc_cpus = [], []
    for _ in range(repeats):
        wall, cpu, _ = run_timed([str(exe_dir / INCREMENTAL_EXE), str(folder), str(WINDOW), str(out), "inc"])
        inc_walls.append(wall)
        inc_cpus.append(cpu)
    inc = read_estimates(out / "inc_estimates.txt")
    rates, rates_warm, cpu_rates = [], [], []
    for _ in range(repeats):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c0 = _self_cpu()
            seq = process(recording, "rotation3", n_events=WINDOW, progress=False)
            cpu = _self_cpu() - c0
        n = sum(w.n_events for w in seq.windows)
        wall = sum(w.seconds for w in seq.windows)
        rates.append(n / wall)
        rates_warm.append(sum(w.n_events for w in seq.windows[1:]) / sum(w.seconds for w in seq.windows[1:]))
        cpu_rates.append(n / cpu)
    row.update(
        eventemin_incremental_events_per_s=n_kept / statistics.median(inc_walls),
        eventemin_incremental_events_per_cpu_s=n_kept / statistics.median(inc_cpus),
        ours_windows=len(seq.windows),
        ours_windows_events_per_s=statistics.median(rates),
        ours_windows_events_per_s_without_first=statistics.median(rates_warm),
        ours_windows_events_per_cpu_s=statistics.median(cpu_rates),
    )
    if gyro is not None and len(inc):
        errors = metrics.angular_velocity_error(inc[:, 1:], np.tile(gyro, (len(inc), 1)))["relative"]
        row["eventemin_incremental_error_median"] = float(np.median(errors))
        ours = metrics.angular_velocity_error(seq.theta, np.tile(gyro, (len(seq.windows), 1)))["relative"]
        row["ours_windows_error_median"] = float(np.median(ours))
    return row


def markdown(rows: list[dict]) -> str:
    def err(r, key):
        return f"{100 * r[key]:.1f}%" if key in r else "-"

    out = [
        "| recording | events (EventEMin / ours) | EventEMin batch: process wall / CPU s | ours: maximize() "
        "wall / CPU s (evaluations) | ours: set-up + maximize() wall s | EventEMin batch estimate (error) | "
        "ours (error) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['recording']} | {r['eventemin_batch_events']} / {r['ours_events']} | "
            f"{r['eventemin_batch_wall_s']:.3f} / {r['eventemin_batch_cpu_s']:.3f} | "
            f"{r['ours_maximize_wall_s']:.3f} / {r['ours_maximize_cpu_s']:.3f} ({r['ours_evaluations']}) | "
            f"{r['ours_setup_and_maximize_wall_s']:.3f} | {r['eventemin_batch_theta']} "
            f"({err(r, 'eventemin_batch_error')}) | {r['ours_theta']} ({err(r, 'ours_batch_error')}) |"
        )
    out += [
        "",
        f"| recording | EventEMin incremental ({WINDOW} events): events/s wall / CPU | ours, {WINDOW}-event "
        "windows: events/s wall (first window included / without it) / CPU | median error EventEMin / ours |",
        "|---|---|---|---|",
    ]
    for r in rows:
        errors = f"{err(r, 'eventemin_incremental_error_median')} / {err(r, 'ours_windows_error_median')}"
        out.append(
            f"| {r['recording']} | {r['eventemin_incremental_events_per_s']:,.0f} / "
            f"{r['eventemin_incremental_events_per_cpu_s']:,.0f} | {r['ours_windows_events_per_s']:,.0f} / "
            f"{r['ours_windows_events_per_s_without_first']:,.0f} / "
            f"{r['ours_windows_events_per_cpu_s']:,.0f} | "
            f"{errors} |"
        )
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--eventemin", required=True, help="EventEMin checkout with its built examples (bin/)"
    )
    parser.add_argument(
        "--data", default="../shared/data", help="the shared recordings (default ../shared/data)"
    )
    parser.add_argument("--out", default="eventemin-results", help="output folder")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement (medians)")
    args = parser.parse_args(argv)
    root = Path(args.eventemin)
    exe_dir = root / "bin"
    missing = [e for e in (BATCH_EXE, INCREMENTAL_EXE) if not (exe_dir / e).is_file()]
    if missing:
        print(
            f"EventEMin comparison skipped: {', '.join(missing)} not found in {exe_dir} (build EventEMin "
            "with -DEventEMin_BATCH_MODE=ON -DEventEMin_INCREMENTAL_MODE=ON; see this module's docstring)"
        )
        return 0
    recordings = []
    cut = Path(args.data) / "ecd_rotation" / "poster_rotation"
    if cut.is_dir():
        gyro = np.loadtxt(cut / "motion.txt")
        recordings.append((cut, "ECD poster_rotation cut (shared data, gyro)", gyro))
    else:
        print(f"{cut} not found: the shared poster_rotation cut is skipped")
    for name in ("poster_rotation", "poster_6dof"):
        folder = root / "dataset" / name
        if folder.is_dir():
            recordings.append((folder, f"EventEMin sample {name}", None))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="eventemin-compare-") as tmp:
        for i, (folder, label, gyro) in enumerate(recordings):
            print(f"{label}: {folder}", flush=True)
            work = Path(tmp) / str(i)
            work.mkdir()
            rows.append(compare(folder, label, exe_dir, work, args.repeats, gyro))
    with (out / "eventemin_compare.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=sorted({k for r in rows for k in r}))
        writer.writeheader()
        writer.writerows(rows)
    text = markdown(rows)
    (out / "eventemin_compare.md").write_text(text)
    print(text)
    print(f"wrote {out / 'eventemin_compare.csv'} and {out / 'eventemin_compare.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
