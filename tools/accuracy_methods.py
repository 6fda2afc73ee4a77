"""The methods of the accuracy benchmark (tools/bench_accuracy.py), each a runner from a simulation to its outputs:
the baselines (direct integration, the complementary filter; the blurry frame and the reconstructor's runners are
in tools/accuracy_harness.py), EDI from edi_live.edi's functions with a given c or with each c estimator of
edi_live.contrast, the list of every method this checkout can run, and the c-search settings of the sweep."""

from __future__ import annotations

import inspect
from typing import Callable

import numpy as np

from edi_live.simulation import Simulation
from tools import baselines as bl
from tools.accuracy_harness import Outputs, _cpu, _edi_on, _events_between, _gt_targets, run_blurry, run_reconstructor


def run_direct(sim: Simulation) -> Outputs:
    cfg = sim.config
    out = Outputs(note="true c")
    mids, lat = _gt_targets(sim)
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        out.deblurred[mids[k]] = (bl.blurry(f), (_cpu() - t0) * 1e3)
        for g in lat.get(k, []):
            t0 = _cpu()
            img = bl.direct_integration(f, sim.events, int(sim.gt_t_us[g]), cfg.c_on, cfg.c_off)
            out.latent[g] = (img, (_cpu() - t0) * 1e3)
    return out


def run_complementary(sim: Simulation, cutoff_hz: float = 0.5) -> Outputs:
    cfg = sim.config
    out = Outputs(note=f"true c, cutoff {cutoff_hz:g} Hz")
    cf = bl.ComplementaryFilter(cfg.width, cfg.height, cfg.c_on, cfg.c_off, cutoff_hz=cutoff_hz)
    ev = sim.events
    # timeline: every output time and every frame arrival (exposure end), in order
    todo = [(int(sim.gt_t_us[g]), 1, g) for g in range(sim.gt_t_us.size)]
    todo += [(f.exposure_end_us, 0, k) for k, f in enumerate(sim.frames)]
    todo.sort()
    last_t = int(ev["t"][0]) - 1 if ev.size else 0
    started = False
    for t, kind, i in todo:
        t0 = _cpu()
        cf.add_events(_events_between(ev, last_t, t)) if started else None
        last_t = t
        if kind == 0:
            cf.add_frame(sim.frames[i])
            started = True
            continue
        if not started:  # before the first frame the filter has nothing to show: use the first frame
            img = bl.blurry(sim.frames[0])
        else:
            img = cf.image_at(t)
        ms = (_cpu() - t0) * 1e3
        (out.deblurred if sim.gt_kind[i] == 0 else out.latent)[i] = (img, ms)
    return out


def run_edi_functions(sim: Simulation, c_on: float | None = None, c_off: float | None = None) -> Outputs:
    """EDI from edi_live.edi's pure functions with a given (default: the simulator's true) c."""
    from edi_live import edi

    cfg = sim.config
    c_on = cfg.c_on if c_on is None else c_on
    c_off = cfg.c_off if c_off is None else c_off
    frames = [edi.blurry_to_float(f.image) for f in sim.frames]
    return _edi_on(sim, sim.events, frames, c_on, c_off, Outputs(note=f"c_on={c_on:g} c_off={c_off:g}"))


def run_edi_estimator(sim: Simulation, make: Callable[[], object], *, c_start: float = 0.2,
                      event_map_tau: float = 0.5) -> Outputs:
    """EDI with c estimated afresh for every APS frame by an edi_live.contrast estimator (no caching).

    The ms per APS frame include everything: level table, event map / event counts the estimator needs,
    the c search and the deblur. Frame 0 has no predecessor: pair-based estimators start from c_start there.
    """
    from edi_live import contrast, edi

    cfg = sim.config
    est = make()
    out = Outputs()
    mids, lat = _gt_targets(sim)
    ev = sim.events
    prev = None
    c = (c_start, c_start)
    cs, evals = [], []
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        b, informative = edi.blurry_to_float(f.image)
        table = edi.build_level_table(ev, cfg.width, cfg.height, f.exposure_start_us, f.exposure_end_us,
                                      segments=True)
        emap = None
        if not getattr(est, "needs_pair", False):
            emap = contrast.event_map(ev, cfg.width, cfg.height, table.ref_t_us, f.exposure_start_us,
                                      f.exposure_end_us, event_map_tau * f.exposure_us)
        cur = contrast.FrameData(b, informative, table, emap)
        pair = None
        if prev is not None and getattr(est, "needs_pair", False):
            n_on, n_off = edi.signed_counts(ev, cfg.width, cfg.height, t0=prev.table.ref_t_us + 1, t1=table.ref_t_us)
            pair = contrast.FramePair(prev, cur, n_on, n_off)
        if "pairs" in inspect.signature(est.estimate).parameters:  # newer protocol: recent pairs, newest last
            got = est.estimate(cur, [pair] if pair is not None else [], c)
        else:
            got = est.estimate(cur, pair, c)
        if got is not None:
            c = (float(got[0]), float(got[1]))
        log_l = edi.deblur_log(b, table, c[0], c[1], informative=informative)
        img = np.exp(log_l)
        out.deblurred[mids[k]] = (img, (_cpu() - t0) * 1e3)
        cs.append(c)
        evals.append(getattr(est, "last_evaluations", 0))
        prev = cur
        state, t_state = log_l.copy(), table.ref_t_us
        for g in lat.get(k, []):
            t0 = _cpu()
            t = int(sim.gt_t_us[g])
            edi.propagate_log(state, _events_between(ev, t_state, t), c[0], c[1])
            t_state = t
            out.latent[g] = (np.exp(state), (_cpu() - t0) * 1e3)
    arr = np.array(cs[1:] or cs)
    out.note = f"c_on={np.median(arr[:, 0]):.3f} c_off={np.median(arr[:, 1]):.3f} (median)"
    if any(evals):
        out.note += f", {np.median(evals):.0f} evals"
    return out


def available_methods() -> list[tuple[str, Callable[[Simulation], Outputs], str]]:
    """(name, runner, group) for every method this checkout can run. group: 'baseline', 'oracle', 'auto'."""
    methods: list[tuple[str, Callable[[Simulation], Outputs], str]] = [
        ("blurry frame", run_blurry, "baseline"),
        ("direct integration", run_direct, "baseline"),
        ("complementary 0.5 Hz", run_complementary, "baseline"),
        ("complementary 5 Hz", lambda s: run_complementary(s, 5.0), "baseline"),
    ]
    try:
        import edi_live.edi  # noqa: F401
        methods.append(("EDI oracle c (edi.py)", run_edi_functions, "oracle"))
    except ImportError:
        pass
    try:
        from edi_live import contrast
    except ImportError:
        contrast = None
    if contrast is not None:
        for est in estimator_names():
            methods.append((f"EDI auto c: {est} (per frame)",
                            lambda s, e=est: run_edi_estimator(s, lambda: contrast.make_estimator(e)), "auto"))
            if "separate" in inspect.signature(contrast.ESTIMATORS[est]).parameters and est == "consistency":
                methods.append((f"EDI auto c: {est}, c_on/c_off (per frame)",
                                lambda s, e=est: run_edi_estimator(s, lambda: contrast.make_estimator(e, separate=True)),
                                "auto"))
    try:
        from edi_live.reconstructor import EdiReconstructor
    except ImportError:
        return methods
    methods.append(("EDI oracle c (reconstructor)",
                    lambda s: run_reconstructor(s, c_on=s.config.c_on, c_off=s.config.c_off), "oracle"))
    methods.append(("EDI default (reconstructor)", lambda s: run_reconstructor(s), "default"))
    del EdiReconstructor
    return methods


def estimator_names() -> list[str]:
    """c estimators that edi_live.contrast offers (its ESTIMATORS registry when present)."""
    try:
        from edi_live import contrast
    except ImportError:
        return []
    reg = getattr(contrast, "ESTIMATORS", None)
    if isinstance(reg, dict):
        return list(reg)
    if isinstance(reg, (list, tuple)):
        return list(reg)
    return []


def sweep_settings() -> list[tuple[str, str, Callable[[Simulation], Outputs]]]:
    """(curve, setting label, runner): c-search resolutions for the run-time/error trade-off curve."""
    try:
        from edi_live import contrast
    except ImportError:
        return []
    out = []
    if "consistency" in contrast.ESTIMATORS:
        for n_grid, tol, px in ((3, 5e-2, 250), (4, 2e-2, 500), (6, 1e-2, 1000), (8, 3e-3, 2000),
                                (10, 1e-3, 4000), (16, 1e-4, 16000)):
            mk = lambda n=n_grid, t=tol, m=px: contrast.make_estimator("consistency", n_grid=n, tol=t, max_pixels=m)
            out.append(("consistency: grid pts / tol / pixels", f"{n_grid}/{tol:g}/{px}",
                        lambda s, mk=mk: run_edi_estimator(s, mk)))
    try:
        import edi_live.reconstructor  # noqa: F401
        for k in (1, 2, 5, 0):
            out.append(("reconstructor default: re-estimate every K frames (0 = on fit-test failure)", f"K={k}",
                        lambda s, k=k: run_reconstructor(s, reestimate_every=k)))
    except ImportError:
        pass
    if "energy" in contrast.ESTIMATORS:
        for tol in (1e-1, 3e-2, 1e-2, 2e-3, 1e-4):
            mk = lambda t=tol: contrast.make_estimator("energy", tol=t)
            out.append(("energy: golden-section tol", f"{tol:g}", lambda s, mk=mk: run_edi_estimator(s, mk)))
    return out
