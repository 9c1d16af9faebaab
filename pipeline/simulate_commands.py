"""``reachwatch simulate``: one run of a closed loop (or of it and the guarded loop) from
one start: the taxi's from a scenario file's start state, or any application's, in an
environment of a run file, from ``--start`` or the application's own start."""

import io

from .commands import (add_loop_source_arguments, check_detector, finite, loop_scenario,
                       output_folder)
from .console import log


def add_parsers(sub):
    sim = sub.add_parser("simulate", help="run the closed loop of a scenario or run file "
                         "from one start; write the trajectory (CSV, NPZ) and a plot")
    add_loop_source_arguments(sim)
    sim.add_argument("--start", type=finite, nargs="+", metavar="X",
                     help="the start state, one value per axis of the application's state "
                     "(the taxi's: px m, py m, theta rad); default: the scenario's "
                     "initial_state for the taxi, the application's start_state otherwise")
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--loop", choices=["nominal", "guarded"], default="nominal",
                     help="guarded: run the loop alone and guarded by the detector and "
                          "fallback switch (needs the scenario's monitor.detector; in a run "
                          "file scenario.monitor.detector); writes their plot instead of the "
                          "trajectory files (the taxi: Fig. 6, .npz and a Meshcat replay)")
    sim.add_argument("--no-meshcat", action="store_true", help="skip the HTML replay")
    sim.set_defaults(func=simulate_command)


def trajectory_columns(application, trajectory):
    """``(names, columns)`` of a run's table: the time, each state axis with its unit
    (an angle in rad written in degrees) and the controller's estimate
    (`Application.estimate_columns`)."""
    import numpy as np
    units = list(application.axis_units) + [""] * len(application.axes)
    names, columns = ["t_s"], [trajectory.time]
    for j, (axis, unit) in enumerate(zip(application.axes, units)):
        in_degrees = unit == "rad"
        names.append(f"{axis}_deg" if in_degrees else f"{axis}_{unit}" if unit else axis)
        columns.append(np.rad2deg(trajectory.state[:, j]) if in_degrees
                       else trajectory.state[:, j])
    k = trajectory.estimate.shape[1]
    estimate = list(application.estimate_columns)
    names += estimate if len(estimate) == k else [f"estimate_{i}" for i in range(k)]
    columns += list(trajectory.estimate.T)
    return names, np.column_stack(columns)


def start_of(application, scenario, start, where):
    """The run's start: ``start`` (``--start``) or the application's `start_state`,
    checked against the application's axes."""
    import numpy as np
    given = "--start" if start is not None else "the application's start_state"
    start = np.asarray(application.start_state(scenario) if start is None else start, float)
    if start.shape != (len(application.axes),) or not np.all(np.isfinite(start)):
        n = start.size
        raise ValueError(f"{given}: {n} value{'s' * (n != 1)} for {where}, whose "
                         f"'{application.name}' state has {len(application.axes)} "
                         f"({', '.join(application.axes)}), each finite")
    return start


def simulate_command(args):
    import numpy as np

    from reachwatch.reach.application import load_application
    from reachwatch.systems.files import atomic_write_bytes
    scenario, spec, where, key = loop_scenario(args)
    application = load_application(spec)
    if args.loop == "guarded":
        check_detector(scenario, where, key)
    start = start_of(application, scenario, args.start, where)
    out = output_folder(args.out)
    if args.loop == "guarded":
        alone, guarded, paths = application.simulate_guarded(
            scenario, start, out, meshcat_html=not args.no_meshcat)
        flags = "" if guarded.anomaly is None else f", {int(np.sum(guarded.anomaly))} flagged ticks"
        speed = "" if guarded.speed is None else f" (min speed {np.min(guarded.speed):.2f} m/s{flags})"
        verdict = {True: application.failure_words,
                   False: f"did not {application.fail_words}"}
        log.info(f"alone: {verdict[bool(alone.failed)]}; guarded: "
                 f"{verdict[bool(guarded.failed)]}{speed}; wrote {', '.join(map(str, paths))}")
        return
    trajectory, failed = application.run_from(scenario, start, scenario.duration)
    name = scenario.environment.name
    header, columns = trajectory_columns(application, trajectory)
    text = io.StringIO()
    np.savetxt(text, columns, delimiter=",", fmt="%.6f", header=",".join(header), comments="")
    atomic_write_bytes(out / f"{name}_trajectory.csv", text.getvalue().encode())
    buffer = io.BytesIO()
    np.savez(buffer, time=trajectory.time, state=trajectory.state,
             estimate=trajectory.estimate, axes=np.array(application.axes, dtype=str),
             failed=failed, failure_time=trajectory.failure_time)
    atomic_write_bytes(out / f"{name}_trajectory.npz", buffer.getvalue())
    verdict = (f"{application.failure_words} at {trajectory.failure_time:.2f} s"
               if failed else f"did not {application.fail_words} in {scenario.duration:g} s")
    plot = application.draw_runs([(trajectory, "closed loop")], scenario=scenario,
                                 path=out / f"{name}_trajectory.png", title=f"{name}: {verdict}")
    log.info(f"{verdict}; wrote {out / (name + '_trajectory.csv')}, .npz and {plot}")
