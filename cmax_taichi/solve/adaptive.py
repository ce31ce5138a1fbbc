"""Motion-adaptive windows: each window holds about as much motion as can be estimated.

A window of a fixed number of events holds as much motion as the scene's event rate gives: 5,000 events
of an ECD rotation cut hold half a pixel (an estimate of noise), 5,000 events of a slow, sparse scene may
hold ten. :class:`AdaptiveWindows` sizes each window by the motion instead: the previous window's
estimate predicts the image speed at the window's extreme pixels (the corners of the bounding box of its
events, :func:`extreme_speed`), and the next window takes the events of the time in which that speed
moves them by ``target_px`` (8 px by default: enough motion to be estimated, little enough that the
motion stays about constant in the window), bounded by ``min_events`` / ``max_events`` and
``max_duration``. The first window has no previous estimate: it starts with ``first_events`` events and
grows (at most ``first_tries`` times, each time to the duration its own estimate predicts, at most
``first_growth`` times longer) until its estimate predicts at least ``accept`` times the target.

Why 8 px at the extreme pixels (the corners; about 5 px at the centre of a DAVIS240 under rotation), and
a first window of 30,000 events: a window is sized by the estimate before it, and the estimate of a
window that holds little motion can overshoot; with a first window of 10,000 events and 3-4 px,
boxes_rotation's windows stayed at 7,000-12,000 events and 28-68% off the gyro (docs/live.md, "Choosing
the target and the first window").

The trade-off: the motion in a window, and so the accuracy of its estimate, no longer depends on the
event rate, but the window's duration does: fast motion gives short windows (more estimates per second,
each of fewer events), slow motion long ones (up to ``max_duration``: fewer estimates, later, and the
constant-motion model of a window strained over a longer time). A sudden change of speed is seen one
window late (the window is sized by the speed before it); the tracking-loss rule of
:func:`cmax_taichi.solve.sequence.process` still runs the global search when a warm start fails.

:class:`AdaptivePlanner` applies the rule to any source of time-ordered events given as two functions
(``time_of(i)``, ``search(t)``), a recording (all events known) or the buffer of a live stream (events
still arriving), and keeps the duration the last estimate predicts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera

__all__ = ["AdaptivePlanner", "AdaptiveWindows", "extreme_speed", "settle_window"]


@dataclass(frozen=True)
class AdaptiveWindows:
    """The motion-adaptive window rule (see the module docstring).

    Parameters
    ----------
    target_px : float
        Displacement (px) that a window should hold at its extreme pixels, as the previous estimate
        predicts it (default 8).
    min_events, max_events : int
        Bounds on a window's events (defaults 2,000 and 500,000). ``max_events`` and ``max_duration``
        are hard bounds; ``min_events`` gives way to ``max_duration`` (a slow event rate then gives
        windows of fewer events).
    max_duration : float
        Longest window, s (default 0.5): a still camera (an estimate of no motion) gets windows of
        this length.
    first_events : int
        Events of the first window's first try (default 30,000, the count windows' default: a first
        estimate has to come from a window that holds enough motion, whatever it is).
    first_tries : int
        Most solves of the first window (default 3).
    first_growth : float
        Most growth of the first window's duration per try (default 4).
    accept : float
        The first window is kept once its estimate predicts at least ``accept * target_px`` over it
        (default 0.7); the last, partial window is estimated when it holds at least that much.
    first_search : str
        How the first window is solved: ``"identity"`` (default), a local ascent from the identity warp
        (a window that holds a few px of motion has its optimum in reach of it; 8-16 evaluations on the
        ECD rotation cuts against 74-83 for the global search, the same estimates), with the global
        search too when the window's estimate predicts more than twice the target over it; or
        ``"global"``, the global search of :func:`~cmax_taichi.maximize`.
    """

    target_px: float = 8.0
    min_events: int = 2_000
    max_events: int = 500_000
    max_duration: float = 0.5
    first_events: int = 30_000
    first_tries: int = 3
    first_growth: float = 4.0
    accept: float = 0.7
    first_search: str = "identity"

    def __post_init__(self) -> None:
        checks.seconds("target_px", self.target_px, positive=True)
        checks.seconds("max_duration", self.max_duration, positive=True)
        checks.seconds("first_growth", self.first_growth, positive=True)
        object.__setattr__(self, "min_events", checks.whole_number("min_events", self.min_events, 2))
        object.__setattr__(self, "max_events", checks.whole_number("max_events", self.max_events, 2))
        object.__setattr__(self, "first_events", checks.whole_number("first_events", self.first_events, 2))
        object.__setattr__(self, "first_tries", checks.whole_number("first_tries", self.first_tries, 1))
        if self.max_events < self.min_events:
            raise ValueError(f"max_events ({self.max_events}) is below min_events ({self.min_events})")
        if not 0 < float(self.accept) <= 1:
            raise ValueError(f"accept must be in (0, 1], got {self.accept}")
        if self.first_growth <= 1:
            raise ValueError(f"first_growth must be above 1, got {self.first_growth}")
        if self.first_search not in ("identity", "global"):
            raise ValueError(f"first_search must be 'identity' or 'global', got {self.first_search!r}")

    def as_dict(self) -> dict:
        """The settings, JSON-friendly (the results' ``settings``)."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


def extreme_speed(prob, theta) -> float:
    """The largest image speed (px/s) that ``theta`` gives at the corners of the bounding box of the
    events of ``prob`` (a :class:`~cmax_taichi.ContrastMaximization`; their undistorted coordinates):
    the warp's flow at each corner, on a one-pixel grid whose centre is moved by the corner's offset (a
    warp's flow depends on a pixel through its offset from the centre that the problem gives it). 0 for
    the identity."""
    from cmax_taichi.pipeline.flow_field import dense_flow

    theta = np.asarray(theta, dtype=np.float64)
    if not np.any(theta):
        return 0.0
    events = prob.events
    (cx, cy), (fx, fy) = prob.setup.center, prob.setup.focal
    speed = 0.0
    for x in (float(np.min(events.x)), float(np.max(events.x))):
        for y in (float(np.min(events.y)), float(np.max(events.y))):
            corner = Camera(fx=fx, fy=fy, cx=cx - x, cy=cy - y)
            flow = dense_flow(prob.model, theta, (1, 1), camera=corner, duration=prob.duration)
            speed = max(speed, float(np.hypot(flow[0, 0, 0], flow[1, 0, 0])))
    return speed


class AdaptivePlanner:
    """Where the windows of :class:`AdaptiveWindows` end over one source of time-ordered events.

    Parameters
    ----------
    rule : AdaptiveWindows
    time_of : callable
        ``time_of(i)``: time (s) of event ``i``.
    search : callable
        ``search(t)``: index of the first event with time ``>= t`` among the events available now (their
        count when none).

    Attributes
    ----------
    duration : float or None
        The duration (s) the last estimate predicts for the next window; None before the first estimate.
    next_start : int
        Where the next window starts: the end of the last window as it was kept (set by the caller).
    """

    def __init__(
        self, rule: AdaptiveWindows, time_of: Callable[[int], float], search: Callable[[float], int]
    ):
        self.rule = rule
        self.time_of = time_of
        self.search = search
        self.duration: float | None = None
        self.next_start = 0
        self.tries = 0  # solves of the first window so far

    def stop(
        self,
        start: int,
        available: int,
        final: bool = False,
        duration: float | None = None,
        t_start: float | None = None,
        tail_duration: float | None = None,
    ) -> int | None:
        """The end (exclusive index) of the window that starts at event ``start``, given ``available``
        events; None when it cannot end yet: the events that decide it have not all arrived, or, when
        ``final`` (no event comes after them), they fall short of it (the rest is a partial tail).

        When ``final``, a window that would leave a tail too short to be estimated on its own
        (:meth:`keeps_tail` at ``tail_duration``, default ``duration``: the windows the motion asks for)
        takes it, within ``max_events`` and ``max_duration``.

        ``duration`` (s) replaces :attr:`duration`; without either (the first window) the window is
        ``first_events`` events long. ``t_start``: the time of event ``start`` when ``time_of`` no longer
        gives it (a live stream's first window, grown past the events already taken)."""
        rule = self.rule
        duration = self.duration if duration is None else duration
        if start >= available:
            return None
        t0 = self.time_of(start) if t_start is None else t_start
        cap = self.search(t0 + rule.max_duration)  # the hard bounds
        hard = min(start + rule.max_events, cap if cap < available else math.inf)
        if duration is None:
            wanted = start + rule.first_events
        else:
            target = self.search(t0 + duration) if math.isfinite(duration) else available
            wanted = max(target, start + rule.min_events) if target < available else math.inf
        stop = min(wanted, hard)
        if stop > available:
            return None
        stop = int(stop)
        tail_duration = duration if tail_duration is None else tail_duration
        if final and stop < available and not self.keeps_tail(stop, available, tail_duration):
            merged_fits = available - start <= rule.max_events and (
                self.time_of(available - 1) - t0 < rule.max_duration
            )
            if merged_fits:
                return available
        return stop

    def keeps_tail(self, start: int, end: int, duration: float | None = None) -> bool:
        """Whether the last, partial window (events ``start:end``) is estimated: it holds at least
        ``min_events`` and, at the speed of the last estimate (``duration``: the window duration it
        predicts, default :attr:`duration`), ``accept`` times the target motion."""
        rule = self.rule
        duration = self.duration if duration is None else duration
        if end - start < max(rule.min_events, 2):
            return False
        if duration is None:
            return True  # no estimate yet: the first window is what there is
        held = self.time_of(end - 1) - self.time_of(start)
        return held >= rule.accept * min(duration, rule.max_duration)

    def predicted(self, speed: float) -> float:
        """The duration (s) in which ``speed`` (px/s) moves the extreme pixels by the target (inf when
        still)."""
        return self.rule.target_px / speed if speed > 0 and math.isfinite(speed) else math.inf

    def predict(self, speed: float) -> float:
        """The duration (s) in which ``speed`` (px/s) moves the extreme pixels by the target (inf when
        still), kept for the next window."""
        self.duration = self.predicted(speed)
        return self.duration

    def retry_duration(self, duration: float, speed: float) -> float | None:
        """Whether the first window grows after a solve: None to keep it (its estimate, moving its extreme
        pixels at ``speed`` px/s over its ``duration`` s, holds at least ``accept`` times the target, or
        the tries are spent); else the duration (s) to grow it to: what its estimate predicts, at most
        ``first_growth`` times ``duration``. The caller ends the window at :meth:`stop` of that duration,
        and keeps it as it is when that is no later."""
        rule = self.rule
        self.tries += 1
        if self.tries >= rule.first_tries or speed * duration >= rule.accept * rule.target_px:
            return None
        wanted = rule.target_px / speed if speed > 0 else math.inf
        return min(wanted, rule.first_growth * max(duration, 1e-9))


def settle_window(planner: AdaptivePlanner, solver, solved: tuple, used, kept, grow: Callable):
    """The adaptive rule after a window's solve, for :func:`~cmax_taichi.solve.sequence.process` and
    :func:`~cmax_taichi.solve.online.run_live` alike.

    The first window grows while its estimate predicts too little motion over it
    (:meth:`AdaptivePlanner.retry_duration`), each time solved again warm from the last try; when it was
    solved from the identity and holds more than twice the target, the global search runs too and the
    better J is kept. Then the next window's duration is what the estimate predicts.

    Parameters
    ----------
    planner : AdaptivePlanner
    solver : WindowSolver
        Holding the window just solved.
    solved : tuple
        ``(result, search, fwl)`` of that solve.
    used, kept
        The window's events and undistortion mask, as solved.
    grow : callable
        ``grow(duration, tail_duration)``: the first window grown to ``duration`` s (a tail shorter than
        ``tail_duration`` s worth of a window joins it), as ``(used, kept, extra)``; None when it cannot
        grow. ``extra`` is the caller's (its span, masks).

    Returns
    -------
    tuple
        ``(result, search, fwl, used, kept, extra)``: the searches joined by ``+`` (``"identity+warm"``),
        the evaluations and seconds of every solve summed; ``extra`` of the last growth, None without.
    """
    res, search, fwl = solved
    searches, extra = [search], None
    speed = extreme_speed(solver.prob, res.theta)

    def add(before, after):
        return replace(after, n_evaluations=before.n_evaluations + after.n_evaluations,
                       seconds=before.seconds + after.seconds)  # fmt: skip

    if planner.duration is None:
        while (longer := planner.retry_duration(solver.prob.duration, speed)) is not None:
            grown = grow(longer, planner.predicted(speed))
            if grown is None:
                break
            used, kept, extra = grown
            solver.retry_from(res)
            before = res
            res, search, fwl = solver.solve(used, kept)
            res = add(before, res)
            searches.append(search)
            speed = extreme_speed(solver.prob, res.theta)
        if searches[0] == "identity" and speed * solver.prob.duration > 2 * planner.rule.target_px:
            # more motion than a local ascent from the identity is sure to reach: the global search too
            full, _, full_fwl = solver.solve(used, kept, "global")
            if full.value > res.value:
                res, fwl, speed = add(res, full), full_fwl, extreme_speed(solver.prob, full.theta)
            else:
                res = add(full, res)
            searches.append("global")
    planner.predict(speed)
    return res, "+".join(dict.fromkeys(searches)), fwl, used, kept, extra
