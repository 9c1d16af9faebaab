"""``reachwatch simulate``: one run of the closed loop (or of it and the guarded loop)
from the scenario's start state."""

import io

from .commands import check_detector, output_folder, scenario_from_args
from .console import log
from .overlays import add_overlay_arguments


def add_parsers(sub):
    sim = sub.add_parser("simulate", help="run the closed loop from the scenario's start "
                         "state; write the trajectory (CSV, NPZ) and a top-view plot")
    sim.add_argument("--scenario", help="scenario YAML (default: built-in defaults)")
    add_overlay_arguments(sim)
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--loop", choices=["nominal", "guarded"], default="nominal",
                     help="guarded: also run the loop guarded by the detector and fallback "
                          "switch (needs monitor.detector in the scenario); writes a Fig.-6 "
                          "plot and a Meshcat replay (.html)")
    sim.add_argument("--no-meshcat", action="store_true", help="skip the HTML replay")
    sim.set_defaults(func=simulate_command)


def _columns(trajectory):
    import numpy as np
    names = ["t_s", "px_m", "py_m", "theta_deg"]
    columns = [trajectory.time, trajectory.state[:, 0], trajectory.state[:, 1],
               np.rad2deg(trajectory.state[:, 2])]
    k = trajectory.estimate.shape[1]
    names += ["px_hat_m", "theta_hat_deg"] if k == 2 else [f"estimate_{i}" for i in range(k)]
    columns += list(trajectory.estimate.T)
    return names, np.column_stack(columns)


def simulate_command(args):
    import numpy as np

    from reachwatch.diagrams import initial_state_vector, make_closed_loop_diagram, simulate
    from reachwatch.diagrams.plots import plot_runway_top_view
    from reachwatch.systems.files import atomic_write_bytes
    from reachwatch.taxi import OffRunway, simulate_guarded
    scenario = scenario_from_args(args, controller=True)
    if args.loop == "guarded":
        check_detector(scenario, args.scenario)
    out = output_folder(args.out)
    if args.loop == "guarded":
        nominal, guarded, paths = simulate_guarded(scenario, out,
                                                   meshcat_html=not args.no_meshcat)
        log.info(f"alone: {'failed' if nominal.failed else 'stayed on the runway'}; "
                 f"guarded: {'failed' if guarded.failed else 'stayed on the runway'} "
                 f"(min speed {guarded.speed.min():.2f} m/s, {int(guarded.anomaly.sum())} "
                 f"flagged ticks); wrote {', '.join(map(str, paths))}")
        return
    diagram = make_closed_loop_diagram(scenario)
    trajectory = simulate(diagram, initial_state=initial_state_vector(scenario.initial_state),
                          duration=scenario.duration, period=scenario.controller.period,
                          failed=OffRunway(scenario.environment.half_width))
    name = scenario.environment.name
    header, columns = _columns(trajectory)
    text = io.StringIO()
    np.savetxt(text, columns, delimiter=",", fmt="%.6f", header=",".join(header), comments="")
    atomic_write_bytes(out / f"{name}_trajectory.csv", text.getvalue().encode())
    buffer = io.BytesIO()
    np.savez(buffer, time=trajectory.time, state=trajectory.state,
             estimate=trajectory.estimate, half_width=scenario.environment.half_width,
             failed=trajectory.failed, failure_time=trajectory.failure_time)
    atomic_write_bytes(out / f"{name}_trajectory.npz", buffer.getvalue())
    verdict = (f"FAILED at {trajectory.failure_time:.2f} s" if trajectory.failed
               else "stayed on the runway")
    plot = plot_runway_top_view([(trajectory, "closed loop")],
                                half_width=scenario.environment.half_width,
                                path=out / f"{name}_trajectory.png", title=f"{name}: {verdict}")
    log.info(f"{verdict}; wrote {out / (name + '_trajectory.csv')}, .npz and {plot}")
