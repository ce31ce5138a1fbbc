"""``cmax-taichi flow --live SOURCE``: the dense flow of each window while the events arrive (a
dv-processing TCP stream, a camera, or a recording replayed at its recorded speed), on the live loop of
``estimate --live`` (:func:`cmax_taichi.flow.live.run_live_flow`).

Output, as each window is done: ``OUT/flow/flow_NNNN.<format>`` (the flow files of a recorded ``flow``
run, each written whole under a hidden name and renamed into place), a line of
``OUT/flow_timestamps.txt`` and the row of ``OUT/results.csv`` (the columns of a recorded run's and
``latency [s]``), appended and flushed: a crash loses at most the window in flight. A window that was
not estimated has its row (``status``; ``behind`` when the estimator had fallen behind and skipped it).
When the run ends (the source ends, ``--idle-timeout``, ``--max-windows``, Ctrl-C or SIGTERM: the window
in flight is finished first), ``OUT/summary.json`` gets the settings, where every event went and the
run's figures (real-time factor, latency median and 99th percentile), and the manifest lists the files.
OUT is checked and locked as for every command.
"""

from __future__ import annotations

import argparse
import math

from cmax_taichi.cli import CliError, _live


def run(args: argparse.Namespace, regs: dict) -> int:
    """``flow --live``: returns the exit code (0; 130 / 143 when Ctrl-C / SIGTERM ended the run)."""
    import numpy as np

    from cmax_taichi.cli.flow import COLUMNS, flow_meta, flow_name, make_estimator, row_fields, run_options
    from cmax_taichi.flow.grid import check_padded_sensor
    from cmax_taichi.flow.live import DenseFlowWindows, run_live_flow
    from cmax_taichi.flow.sequence import check_sensor
    from cmax_taichi.io.writers import write_flow

    if args.path is not None or args.example is not None:
        raise CliError("--live SOURCE replaces PATH and --example")
    if args.figures is not None:
        raise CliError("--figures: not with --live (--display shows the windows as they are done)")
    _, windows = _live.window_rule(args, live_default="count")
    live = _live.LiveSource(args)
    estimator = make_estimator(args, regs)
    patterns = (f"flow/flow_*.{args.flow_format}", "flow_timestamps.txt", "results.csv", "summary.json")
    output = _live.LiveOutput(args.out, live.inputs, COLUMNS, command="flow --live", patterns=patterns)
    with output as out:  # OUT checked and locked before anything opens
        _live.common_init(args)
        stream = live.open()
        try:  # the grids and the IWE's size, before the first row
            if args.padding is not None:
                check_padded_sensor(stream.sensor_size, args.padding, "--padding")
            check_sensor(estimator, stream.sensor_size)
        except ValueError as exc:
            stream.close()
            raise CliError(f"--live {live.source}: {exc}") from None
        shown = _live.LiveDisplay() if live.display else None

        def on_window(row, est, res, latency):
            if row.estimated:
                meta = flow_meta(args, row, {})
                out.write_file(flow_name(args, row), lambda path: write_flow(path, row.displacement, **meta))
                out.append("flow_timestamps.txt", f"{meta['t_start']:.9f} {meta['t_end']:.9f}\n")
            out.write(row_fields(row), latency)
            if shown is not None:
                median = np.median(res.nodes.reshape(-1, 2), axis=0)
                shown.offer(row, median, DenseFlowWindows.param_names, DenseFlowWindows.units,
                            lambda: _images(est, row, res))  # fmt: skip

        def on_skipped(row):
            out.write(row_fields(row), math.nan)

        grid = f"dense flow ({args.grid[0]}x{args.grid[1]} cells, {args.levels} levels)"
        _live.announce(stream, grid, out)
        result, error, signum = _live.drive(
            lambda stop: run_live_flow(
                stream, estimator, windows=windows, dt=args.dt, warm_start=not args.no_warm_start,
                max_windows=args.max_windows, idle_timeout=args.idle_timeout, stop=stop, on_window=on_window,
                on_skipped=on_skipped,
            ),
            shown,
        )  # fmt: skip
        summary = {**_live.summary(result), "options": run_options(args, regs)}
        files = out.finish(summary, "summary.json", with_rows=False)
    flows = [p for p in files if p.parent.name == "flow"]
    listed = [str(p) for p in files if p.parent.name != "flow"]
    if flows:
        listed.append(f"{args.out}/flow/flow_*.{args.flow_format} ({len(flows)} files)")
    _live.print_summary(result, listed)
    return _live.exit_code(result, error, signum, out.rows, files[0])


def _images(estimator, row, res):
    """The IWE of the window of ``row`` at zero flow and at its flow (the display's two images)."""
    import numpy as np

    prob = estimator.problem(row.events, 1)
    prob.set_grid(res.grid)
    return prob.iwe(np.zeros(res.grid.shape)), prob.iwe(res.nodes)
