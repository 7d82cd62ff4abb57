"""The `workbench` command line: estimate, score, serve, make-scenes, bench."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from workbench.errors import InputError, check_count
from workbench.evaluation.pool import check_run_memory, check_workers
from workbench.inference.config import MAX_ITERATIONS, MAX_PARTICLES, METHODS, EstimatorConfig, check_seed
from workbench.inference.search.moves.registry import PROPOSALS
from workbench.inference.smc.particles import STATES, Sigma
from workbench.label.config import LabelConfig
from workbench.physics import BACKENDS, PhysicsConfig, check_backend
from workbench.problem.problem import ProblemConfig
from workbench.render.likelihood import LikelihoodConfig
from workbench.synth.sensor.model import DEFAULT_SENSOR, SENSOR_NAMES
from workbench.track.config import TrackConfig

DEMO_DATASET = Path(__file__).resolve().parent.parent / "assets" / "demo"
ESTIMATOR_DEFAULTS = EstimatorConfig()
TRACK_DEFAULTS = TrackConfig()
LABEL_DEFAULTS = LabelConfig()
# Upper bounds of the other counts, each with its reason (the estimator's own: inference.config).
MAX_RETRIES = 100  # a worker that died 100 times will die again: out of memory, or a broken install
MAX_TRACK_ITERATIONS = 1000  # a tracked frame runs 2 (6 with an object lost); 1000 take many minutes per frame
MAX_REPEATS = 1000  # bench --speed: the median of 1000 repeats is as steady as it gets
MAX_SCENES = 100_000  # make-scenes, bench: scenes per category, and frames per sequence (an hour of video at 30 fps)


def _add_estimator_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", choices=METHODS, default="pipf", help="PI-PF or PI-MCPF (default: pipf)")
    p.add_argument("--particles", type=int, default=ESTIMATOR_DEFAULTS.particles,
                   help=f"particles N (paper: 1444; default {ESTIMATOR_DEFAULTS.particles})")
    p.add_argument("--iterations", type=int, default=ESTIMATOR_DEFAULTS.iterations,
                   help=f"maximum iterations (default {ESTIMATOR_DEFAULTS.iterations})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--state", choices=STATES, default="6dof", help="6dof, or the paper's reduced x,y,z,yaw")
    p.add_argument("--proposals", choices=PROPOSALS, default="default",
                   help="default: data-driven starts and moves (one object at a time, resting faces, turns, "
                        "stacking, ICP); paper: random starts and Gaussian diffusion only, as Desingh et al.")
    p.add_argument("--likelihood", choices=("robust", "ssd"), default="robust")
    p.add_argument("--clutter-floor", type=clutter_floor_arg, default=LikelihoodConfig.clutter_floor,
                   metavar="LOG_DENSITY",
                   help="robust likelihood: what a reading of a piece of unmodelled clutter that the objects do not "
                        f"claim scores at least (default {LikelihoodConfig.clutter_floor}; 'none': an outlier, as "
                        "before; see docs/design.md, The likelihood)")
    p.add_argument("--floor-from", type=float, default=EstimatorConfig.floor_from, metavar="SHARE",
                   help="with --clutter-floor: the share of the iterations searched without the floor before it "
                        f"is weighed in (default {EstimatorConfig.floor_from})")
    p.add_argument("--sigma-pos", type=float, default=0.01, help="diffusion of x and y, metres")
    p.add_argument("--sigma-z", type=float, default=0.01, help="diffusion of elevation, metres")
    p.add_argument("--sigma-deg", type=float, default=5.0, help="diffusion of roll, pitch, yaw, degrees")
    p.add_argument("--workers", type=int, default=2, help="evaluation worker processes (default 2)")
    p.add_argument("--max-render-pixels", type=int, default=160 * 120, help="pixels per rendered hypothesis")
    p.add_argument("--no-early-stop", action="store_true", help="run all iterations even after convergence")
    _add_budget_arg(p, "each frame")
    p.add_argument("--leaning", action=argparse.BooleanOptionalAction, default=True,
                   help="polish also tries objects laid along slanted flat patches, as an object leaning on another "
                        "shows (default on; see docs/design.md, The search)")
    p.add_argument("--no-settle", action="store_true",
                   help="return the search's estimate as physics put it, not fitted to the depth at the end "
                        "(within 1.5 cm and 12 degrees; see docs/design.md, Settling)")
    _add_physics_arg(p)


def _add_physics_arg(p: argparse.ArgumentParser, default: str | None = PhysicsConfig.backend) -> None:
    p.add_argument("--physics", choices=BACKENDS, default=default,
                   help=f"the simulator hypotheses are settled in (default {PhysicsConfig.backend}; mujoco needs the "
                        "extra: pip install 'workbench[mujoco]')")


def physics_config(args: argparse.Namespace) -> PhysicsConfig:
    """``--physics`` -> the PhysicsConfig; InputError, before any work, when its simulator is not installed."""
    physics = PhysicsConfig(backend=args.physics or PhysicsConfig.backend)
    check_backend(physics)
    return physics


def estimator_config(args: argparse.Namespace) -> EstimatorConfig:
    a = np.radians(args.sigma_deg)
    return EstimatorConfig(
        method=args.method,
        particles=args.particles,
        iterations=args.iterations,
        sigma=Sigma(args.sigma_pos, args.sigma_pos, args.sigma_z, a, a, a),
        state=args.state,
        seed=args.seed,
        proposals=args.proposals,
        floor_from=args.floor_from,
        leaning=args.leaning,
        budget_s=args.budget,
        **({"settle_shift": 0.0} if args.no_settle else {}),
    )


def _add_budget_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                   help=f"anytime: {what} stops searching by this wall time and answers with its best scene so far, "
                        "its posterior saying what was cut short (default: until converged; see docs/guide.md)")


def _add_engine_args(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help=f"local: {what} here; ray: on a Ray cluster (needs the extra: pip install 'workbench[ray]')")
    p.add_argument("--ray-address", default=None, metavar="auto|HOST:PORT",
                   help="join this Ray cluster (auto: the one `ray start` started on this machine); default: start "
                        "Ray on this machine for the run")


def ray_config(args: argparse.Namespace):
    """``--engine``/``--ray-address``/``--max-retries`` -> an evaluation.ray.RayConfig, or None for the local engine;
    InputError, before any work, when Ray is asked for and not installed."""
    from workbench.evaluation.ray import RayConfig, check_reachable, require_ray

    if args.engine == "local":
        if args.ray_address is not None:
            raise InputError("--ray-address", "joins a Ray cluster: use it with --engine ray")
        return None
    check_reachable(args.ray_address)  # a malformed address first: it is wrong with or without Ray
    require_ray()
    retries = getattr(args, "max_retries", RayConfig.max_retries)
    check_count(retries, "--max-retries", low=0, high=MAX_RETRIES)
    return RayConfig(address=args.ray_address, max_retries=retries)


def clutter_floor_arg(text: str) -> float | None:
    """``--clutter-floor``: a number, or "none"."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a log-density or 'none', got {text!r}") from None


def run_settings(args: argparse.Namespace) -> tuple[EstimatorConfig, ProblemConfig]:
    """The estimator's and the problem's settings of a command that runs the estimator (estimate, track, label),
    checked with its --workers before anything is loaded or started."""
    config, problem = estimator_config(args), problem_config(args)
    config.validate("")
    problem.validate()
    check_workers(args.workers)
    return config, problem


def problem_config(args: argparse.Namespace) -> ProblemConfig:
    likelihood = LikelihoodConfig(model=args.likelihood, clutter_floor=args.clutter_floor)
    return ProblemConfig(max_render_pixels=args.max_render_pixels, likelihood=likelihood, physics=physics_config(args))


def _cmd_estimate(args: argparse.Namespace) -> int:
    if args.dataset is None:
        raise InputError(None, "name a BOP dataset folder (or use `workbench estimate assets/demo`)")
    # Every setting and the output path are checked before anything is loaded or started.
    config, problem = run_settings(args)
    check_count(args.max_retries, "--max-retries", low=0, high=MAX_RETRIES)
    check_run_memory(config.particles, problem.max_render_pixels)
    ray = ray_config(args)
    posterior, results = _open_outputs(args)
    try:
        return _estimate_into(results, args, config, problem, ray, posterior)
    finally:
        results.close()
        if posterior is not None:
            posterior.close()


def _open_outputs(args: argparse.Namespace):
    """``estimate``'s and ``track``'s output files, checked to be two different files and each locked for the run
    -> (the PosteriorFile or None, the ResultsFile)."""
    from workbench.io.outputs import check_distinct
    from workbench.io.results import PosteriorFile, ResultsFile

    check_distinct({"--out": args.out, "--posterior": args.posterior})
    if args.posterior is not None:
        check_posterior_made(args)
    posterior = (None if args.posterior is None else
                 PosteriorFile.open(args.posterior, force=args.force, resume=args.resume))
    try:
        return posterior, ResultsFile.open(args.out, force=args.force, resume=args.resume)
    except BaseException:
        if posterior is not None:
            posterior.close()
        raise


def check_posterior_made(args: argparse.Namespace) -> None:
    """InputError when ``--posterior`` is asked of a search that makes none: the posterior comes from settling the
    estimate (``DefaultSearch.finish``), which --no-settle and the paper's search leave out; the file would never
    be written."""
    for given, why in ((args.no_settle, "--no-settle"), (args.proposals == "paper", "--proposals paper")):
        if given:
            raise InputError("--posterior", f"the posterior is made while the estimate is settled, which {why} "
                                            f"leaves out: no file would be written; drop --posterior or {why}")


def _estimate_into(results, args: argparse.Namespace, config: EstimatorConfig, problem: ProblemConfig, ray,
                   posterior=None) -> int:
    """``estimate``'s frames, once its settings are checked and its results file is open."""
    from workbench.io import bop
    from workbench.io.results import check_resumed
    from workbench.run.runner import estimate_frames

    frames = bop.list_frames(args.dataset, split=args.split)
    if args.scene is not None:
        frames = [f for f in frames if f[0] == args.scene]
    if args.frame is not None:
        frames = [f for f in frames if f[1] == args.frame]
    if not frames:
        named = " ".join(f"--{k} {v}" for k, v in (("scene", args.scene), ("frame", args.frame)) if v is not None)
        raise InputError(args.dataset, f"no frame matches {named}" if named else
                         f"has no frames{f' in the split {args.split!r}' if args.split else ''} to estimate")
    check_resumed(results, args.dataset, args.split)
    todo = [f for f in frames if f not in results.done()]
    if len(todo) < len(frames):
        print(f"resuming: {len(frames) - len(todo)} of {len(frames)} frame(s) already in {args.out}", file=sys.stderr)
    if not todo:
        return 0
    failures = []
    rows = estimate_frames(
        args.dataset, todo, config, problem, args.workers,
        split=args.split, object_ids=args.objects, early_stop=not args.no_early_stop,
        on_frame=results.add if posterior is None else lambda rows: (results.add(rows), posterior.add(rows)),
        ray=ray, on_failure=failures.append, max_retries=args.max_retries,
    )
    print(f"wrote {len(rows)} result rows for {len(todo) - len(failures)} frame(s) to {args.out}", file=sys.stderr)
    if failures:
        print(f"workbench: error: {len(failures)} of {len(todo)} frame(s) failed (each named above); the others are "
              f"in {args.out}. Fix them and run again with --resume to estimate only those.", file=sys.stderr)
        return 1
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    from workbench.track.frames import sequence_frames, sequence_world

    # Every setting, the frames and the output paths are checked before anything is loaded or started.
    config, problem = run_settings(args)
    check_count(args.max_retries, "--max-retries", low=0, high=MAX_RETRIES)
    check_count(args.track_particles, "--track-particles", low=1, high=MAX_PARTICLES)
    check_count(args.track_iterations, "--track-iterations", low=1, high=MAX_TRACK_ITERATIONS)
    track = TrackConfig(particles=args.track_particles, iterations=args.track_iterations, motion=args.motion)
    track.validate()
    check_run_memory(config.particles, problem.max_render_pixels)
    check_run_memory(track.re_search_particles, problem.max_render_pixels, "--track-particles")
    ray = ray_config(args)
    sequences = {}
    for scene in dict.fromkeys(args.scene):  # each scene once, in the order given
        sequences[scene] = sequence_frames(args.dataset, scene, args.split, args.frames)
        # The camera poses, if given, all there.
        sequence_world(args.dataset, scene, args.split, args.motion, sequences[scene])
    from workbench.io.results import check_resumed
    from workbench.track.run import track_sequences

    posterior, results = _open_outputs(args)
    failures = []
    try:
        check_resumed(results, args.dataset, args.split)
        done = {s: {i for d, i in results.done() if d == s} & set(frames) for s, frames in sequences.items()}
        kept = sum(len(d) for d in done.values())
        if kept:
            print(f"resuming: {kept} of {sum(len(f) for f in sequences.values())} frame(s) already in {args.out}",
                  file=sys.stderr)

        def write(result) -> None:
            results.add(result.rows)
            if posterior is not None:
                posterior.add(result.rows)

        tracked = track_sequences(args.dataset, sequences, done, config, track, problem, args.workers, args.split,
                                  args.objects, not args.no_early_stop, args.max_retries, write, ray,
                                  failures.append)
    finally:
        results.close()
        if posterior is not None:
            posterior.close()
    print(f"wrote the result rows of {tracked} frame(s) to {args.out}", file=sys.stderr)
    if failures:
        print(f"workbench: error: {len(failures)} of {len(sequences)} sequence(s) failed (each named above); the "
              f"others are in {args.out}. Fix them and run again with --resume to track only those.", file=sys.stderr)
        return 1
    return 0


def _cmd_label(args: argparse.Namespace) -> int:
    from workbench.label import run as labelling
    from workbench.label.sequence import label_files, read_keyed, write_sequence
    from workbench.track.frames import sequence_frames, sequence_world

    # Every setting, the frames and the files written are checked before anything is loaded or started.
    config, problem = run_settings(args)
    check_run_memory(config.particles, problem.max_render_pixels)
    track = TrackConfig(motion=args.motion)
    label = LabelConfig(fit_frames=args.fit_frames, snap=args.snap, ends=_ends(args.end))
    label.validate()
    frames = sequence_frames(args.dataset, args.scene, args.split, args.frames)
    sequence_world(args.dataset, args.scene, args.split, args.motion, frames)
    files = label_files(args.dataset, args.scene, args.split, args.out_labels, args.overwrite_gt)
    for path in (files.labels, files.info):
        read_keyed(path)  # a file the labels cannot be merged into is refused now, not after the work
    run = labelling.label_sequence(args.dataset, args.scene, frames, config, track, label, problem, args.workers,
                                   args.split, args.objects, not args.no_early_stop)
    written = write_sequence(files, run.labels, run.infos, run.checks, run.rest_shift)
    table = labelling.flag_table(run)
    if table:
        print("flagged frames (review them in `workbench serve`):", file=sys.stderr)
        print("\n".join(table), file=sys.stderr)
    for obj_id, start in labelling.gone_from(run).items():
        print(f"object {obj_id} is seen through from frame {start} to the end: taken out? End its label there "
              f"with --end {obj_id}:{start - 1}", file=sys.stderr)
    print(labelling.summary(run), file=sys.stderr)
    print(f"wrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    return 0


def _ends(values: list[str] | None) -> dict[int, int]:
    """``--end OBJ:FRAME`` values -> object id -> the last frame of its label."""
    out = {}
    for v in values or []:
        try:
            obj_id, last = (int(x) for x in v.split(":"))
        except ValueError:
            raise InputError("--end", f"must be OBJ:FRAME, an object id and its label's last frame (e.g. 5:10), "
                                      f"got {v!r}") from None
        out[obj_id] = last
    return out


def _cmd_score(args: argparse.Namespace) -> int:
    import json

    from workbench.io.results import read_results_csv
    from workbench.score.scoring import report, score_results, summary
    from workbench.score.vsd import VSDConfig

    if not args.dataset.is_dir():
        raise InputError(args.dataset, "no such dataset folder")
    from workbench.io.outputs import check_distinct

    check_distinct({"the results CSV being scored": args.results, "--json": args.json,
                    "--reliability": args.reliability})
    if args.json is not None:  # before any scoring: --json gets the guards of every file a command writes
        from workbench.io.outputs import check_output_file

        check_output_file(args.json, ours=_is_score_json, force=args.force, what="a score JSON", flag="--json")
    if args.reliability is not None:
        from workbench.io.outputs import check_output_file

        check_output_file(args.reliability, ours=lambda p: p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n",
                          force=args.force, what="a reliability diagram", flag="--reliability")
    from workbench.meshes.heavy import announced

    vsd = VSDConfig()  # BOP's: tau 20 mm, theta 0.3, delta 15 mm; AR_VSD's grid
    with announced(f"scoring {args.results}", cached=False):  # a million rows take minutes: never silent for long
        frames = score_results(args.dataset, read_results_csv(args.results), split=args.split,
                               results_path=args.results, vsd=vsd)
    print("\n".join(report(frames, vsd)))
    if args.reliability is not None:
        from workbench.score.calibration import reliability_png

        reliability_png([m for f in frames for m in f.modes], args.reliability, f"{args.results.name}")
        print(f"# reliability diagram of the top mode: {args.reliability}")
    if args.json is not None:
        objects = [o.to_dict() for f in frames for o in f.objects]
        # NaN is not JSON: an object without an estimate has null errors
        objects = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in o.items()}
                   for o in objects]
        from workbench.io.outputs import write_file

        write_file(args.json, json.dumps({"dataset": str(args.dataset), "results": str(args.results),
                                          "objects": objects, "summary": summary(frames, vsd)}, indent=1))
    return 0


def _is_score_json(path: Path) -> bool:
    """A file `workbench score --json` wrote."""
    from workbench.io.readers import read_json

    document = read_json(path)
    # "summary" came with VSD: a score JSON written before it is ours too
    return isinstance(document, dict) and set(document) - {"summary"} == {"dataset", "results", "objects"}


def _cmd_serve(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from workbench.app.ui.server import DEFAULT_CONFIG, serve

    dataset = DEMO_DATASET if args.demo or args.dataset is None else args.dataset
    check_count(args.port, "--port", low=1, high=65535)
    ray = ray_config(args)
    run = {k: v for k, v in (("method", args.method), ("particles", args.particles),
                             ("iterations", args.iterations), ("budget_s", args.budget)) if v is not None}
    if args.session is not None:
        from workbench.sessions.store import load_session

        state = load_session(args.session)  # a bad session file is an input error here, before any server starts
        _check_session_frame(args.session, state)
        check_backend(state.problem_config.physics)  # a session settled in MuJoCo needs it here too
        if args.dataset is not None or args.demo:
            raise InputError("--session", "a session names its own frame: give no dataset or --demo with it")
        given = [f"--{k.removesuffix('_s')}" for k in run] + (["--physics"] if args.physics is not None else [])
        if given:
            raise InputError("--session", "a session brings its own run settings: give no "
                             + ", ".join(given) + " with it")
    elif dataset != DEMO_DATASET:
        _check_frame_exists(dataset, args.scene, args.frame)
    if args.sessions_dir is not None:
        from workbench.sessions.store import check_sessions_dir

        check_sessions_dir(args.sessions_dir)
    config = replace(DEFAULT_CONFIG, **run)
    config.validate("")  # before any server starts
    physics = physics_config(args)
    check_run_memory(config.particles, ProblemConfig().max_render_pixels)
    if not _is_loopback(args.host):
        print(f"WARNING: serving on {args.host}, not this machine alone: anyone who can reach port {args.port} can "
              "run estimates here, and write labels (scene_gt.json) into the dataset and sessions into the "
              "sessions folder; serve on 127.0.0.1 unless that is meant", file=sys.stderr, flush=True)
    serve(dataset=dataset, scene_id=args.scene, im_id=args.frame, host=args.host, port=args.port,
          session=args.session, sessions_dir=args.sessions_dir, config=config, ray=ray, physics=physics)
    return 0


def _is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine alone (127.0.0.0/8, ::1, localhost): the server is open to no one else."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def _check_session_frame(session: Path, state) -> None:
    """The dataset files a session was made from are all there (changed ones are the app's question: load anyway?);
    InputError naming the session and the first missing file otherwise, before any server starts."""
    from workbench.sessions.store import check_dataset

    missing = [p for p in check_dataset(state) if p.endswith(("missing", "dataset folder not found"))]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise InputError(session, f"the frame it was saved on can no longer be loaded: {missing[0]}{more}")


def _check_frame_exists(dataset: Path, scene_id: int | None, im_id: int | None) -> None:
    """The dataset has the frame ``serve`` is asked for (None: its first), so that a wrong path ends here."""
    from workbench.io import bop

    frames = bop.list_frames(dataset)
    scenes = sorted({s for s, _ in frames})
    if scene_id is not None and scene_id not in scenes:
        raise InputError(dataset, f"no scene {scene_id} (scenes: {scenes[:20]})")
    scene_id = scenes[0] if scene_id is None else scene_id
    in_scene = [i for s, i in frames if s == scene_id]
    if im_id is not None and im_id not in in_scene:
        raise InputError(dataset, f"no frame {im_id} in scene {scene_id} (frames: {in_scene[:20]})")


def _cmd_make_scenes(args: argparse.Namespace) -> int:
    from workbench.synth import make_demo, make_scenes

    check_seed(args.seed)
    check_count(args.per_category, "--per-category", low=1, high=MAX_SCENES)
    t0 = time.perf_counter()
    if args.demo:
        make_demo(args.out, seed=args.seed, force=args.force)
        print(f"wrote the demo scene to {args.out}", file=sys.stderr)
        return 0
    if args.sequence is not None:
        return _make_sequences(args, t0)
    for flag, value, what in (("--push", args.push, "pushes an object"), ("--take-out", args.take_out,
                                                                            "takes an object out"),
                              ("--handle", args.handle, "turns a mug's hidden handle into view")):
        if value is not None:
            raise InputError(flag, f"{what} in a sequence: use it with --sequence N")
    scenes = make_scenes(args.out, [c.strip() for c in args.categories.split(",")], args.per_category, args.seed,
                         distractors=args.distractors, table_pose=args.table_pose, force=args.force,
                         models=args.models, sensor=args.sensor)
    print(f"wrote {len(scenes)} scenes to {args.out} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0


def _make_sequences(args: argparse.Namespace, t0: float) -> int:
    """``make-scenes --sequence N``: each scene as a sequence of N frames on an arc (``synth.sequence``)."""
    from workbench.synth.sequence import Push, TakeOut, make_sequences

    check_count(args.sequence, "--sequence", low=1, high=MAX_SCENES)
    if not (np.isfinite(args.arc) and 0.0 <= args.arc <= 180.0):
        raise InputError("--arc", f"must be degrees in [0, 180], got {args.arc}")
    if args.models is not None or args.distractors is not None or args.table_pose is not None:
        raise InputError("--sequence", "draws its scenes from the categories' own settings: give no --models, "
                                       "--distractors or --table-pose with it")
    if not (np.isfinite(args.push_distance) and 0.0 < args.push_distance <= 0.5):
        raise InputError("--push-distance", f"must be metres in (0, 0.5], got {args.push_distance}")
    push = None if args.push is None else Push(args.push, args.push_distance)
    take_out = None
    if args.take_out is not None:
        try:
            k, j = args.take_out.split(":")
            take_out = TakeOut(int(k), int(j) if j.strip() else None)
        except ValueError:
            raise InputError("--take-out", f"must be K:J, two frames (e.g. 3:5), or K: (never back), got "
                                           f"{args.take_out!r}") from None
    scenes = make_sequences(args.out, [c.strip() for c in args.categories.split(",")], args.per_category,
                            args.sequence, args.seed, arc_deg=args.arc, push=push, force=args.force,
                            take_out=take_out, handle=args.handle, sensor=args.sensor)
    print(f"wrote {len(scenes)} sequences of {args.sequence} frames to {args.out} in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    check_workers(args.workers)
    check_count(args.repeats, "--repeats", low=1, high=MAX_REPEATS)
    for name, high in (("particles", MAX_PARTICLES), ("iterations", MAX_ITERATIONS), ("per_category", MAX_SCENES)):
        if getattr(args, name) is not None:
            check_count(getattr(args, name), "--" + name.replace("_", "-"), low=0 if name == "iterations" else 1,
                        high=high)
    physics = physics_config(args).backend
    if args.speed:
        from workbench.bench.speed import run_speed_benchmark

        if args.engine != "local":
            raise InputError("--engine", "--speed measures this machine's evaluation speed: it runs locally only")
        if args.dataset is not None and not args.dataset.is_dir():
            raise InputError(args.dataset, "no such dataset folder")
        run_speed_benchmark(particles=args.particles, workers=args.workers, repeats=args.repeats,
                            dataset=args.dataset, physics=physics)
        return 0
    if args.profile:
        return _bench_profile(args)
    from workbench.bench.tables import run_benchmark

    ray = ray_config(args)
    if args.dataset is None:
        raise InputError(None, "name a dataset made by `workbench make-scenes`, or pass --speed")
    _check_bench_out(args.out, [m.strip() for m in args.methods.split(",")])
    categories = None if args.categories is None else [c.strip() for c in args.categories.split(",")]
    run_benchmark(args.dataset, args.out, quick=args.quick, methods=[m.strip() for m in args.methods.split(",")],
                  particles=args.particles, iterations=args.iterations, workers=args.workers, state=args.state,
                  categories=categories, per_category=args.per_category, early_stop=not args.no_early_stop,
                  proposals=args.proposals, ray=ray, max_retries=args.max_retries, physics=physics)
    return 0


def _bench_profile(args: argparse.Namespace) -> int:
    """``bench --profile``: one frame estimated as `estimate` would (its defaults, or --particles, --iterations,
    --budget), or tracked from --tracked-from on as `track` would, its time by stage printed and, with --png,
    drawn."""
    from workbench.bench.profile import profile_frame, profile_png, profile_table, profile_tracked
    from workbench.bench.speed import machine_line
    from workbench.io.outputs import check_output_file

    if args.engine != "local":
        raise InputError("--engine", "--profile times this machine: it runs locally only")
    if args.dataset is None or not args.dataset.is_dir():
        raise InputError(args.dataset, "--profile needs a BOP dataset folder")
    if args.scene is None or args.frame is None:
        raise InputError("--profile", "name the frame: --scene S --frame F")
    if args.png is not None:
        check_output_file(args.png, ours=lambda p: p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", force=args.force,
                          what="a profile PNG", flag="--png")
    overrides = {k: v for k, v in (("particles", args.particles), ("iterations", args.iterations),
                                   ("budget_s", args.budget)) if v is not None}
    config = EstimatorConfig(**overrides)
    config.validate("")
    _check_frame_exists(args.dataset, args.scene, args.frame)
    if args.tracked_from is None:
        profile = profile_frame(args.dataset, args.scene, args.frame, config, args.workers)
        how = ""
    else:
        from workbench.track.frames import sequence_frames

        if not args.tracked_from < args.frame:
            raise InputError("--tracked-from", f"must be an image id before --frame {args.frame}, got "
                                               f"{args.tracked_from}")
        frames = sequence_frames(args.dataset, args.scene, None, f"{args.tracked_from}:{args.frame}")
        profile = profile_tracked(args.dataset, args.scene, frames, config, TrackConfig(), args.workers)
        how = f" --tracked-from {args.tracked_from}"
    print(f"# workbench bench --profile {args.dataset} --scene {args.scene} --frame {args.frame}{how}: "
          f"{machine_line()}")
    print("\n".join(profile_table(profile)))
    if args.png is not None:
        profile_png([profile], args.png, f"{args.dataset.name} frame {profile.frame}")
        print(f"wrote {args.png}", file=sys.stderr)
    return 0


def _check_bench_out(out: Path, methods: list[str]) -> None:
    """``bench --out`` is a folder of our tables and CSVs: never a file, never inside a dataset's folders, and the
    files it writes there replace only those an earlier bench wrote (the guards of every output file)."""
    from workbench.bench.tables import is_report_json, is_report_md
    from workbench.io.outputs import check_output_file, dataset_folder_of
    from workbench.io.results import is_results_csv

    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file: --out names the folder the tables are written to")
    inside = dataset_folder_of(out / "x")
    if inside is not None:
        raise InputError(out, f"lies in the dataset folder {inside}: choose an --out outside the dataset")
    for name, ours in [("report.md", is_report_md), ("report.json", is_report_json),
                       *((f"results_{m}.csv", is_results_csv) for m in methods)]:
        check_output_file(out / name, ours=ours, what="a file `workbench bench` wrote", flag="--out", can_force=False)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="workbench", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("estimate", help="estimate object poses in BOP frames, write a BOP results CSV")
    p.add_argument("dataset", type=Path, nargs="?", help="BOP dataset folder (root or split folder)")
    p.add_argument("--split", default=None, help="split folder (default: test, or the only one)")
    p.add_argument("--scene", type=int, default=None, help="scene id (default: all)")
    p.add_argument("--frame", type=int, default=None, help="image id (default: all)")
    p.add_argument("--objects", type=int, nargs="+", default=None, help="object ids present (default: scene_gt.json)")
    p.add_argument("--out", type=Path, default=Path("results.csv"),
                   help="results CSV, written after every frame (default results.csv)")
    p.add_argument("--force", action="store_true", help="replace --out even if it is not a results CSV of ours")
    p.add_argument("--resume", action="store_true", help="keep the frames already in --out and estimate the rest")
    p.add_argument("--posterior", type=Path, default=None, metavar="FILE.json",
                   help="also write each object's modes (pose, probability, log-likelihood gap), position spread and "
                        "open rotation range per frame as JSON")
    _add_estimator_args(p)
    _add_engine_args(p, "frames one after another")
    p.add_argument("--max-retries", type=int, default=3,
                   help="times a dead worker is started again: --engine local, per batch (its part retried); "
                        "--engine ray, per frame (default 3)")
    p.set_defaults(func=_cmd_estimate)

    p = sub.add_parser("track", help="estimate the frames of one scene in order, each from the previous one")
    p.add_argument("dataset", type=Path, help="BOP dataset folder (root or split folder)")
    p.add_argument("--split", default=None, help="split folder (default: test, or the only one)")
    p.add_argument("--scene", type=int, nargs="+", required=True,
                   help="scene id(s), each a sequence: one after another, or with --engine ray each one task, side by "
                        "side")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="image ids A to B, both included, every one present (default: all of the scene's)")
    p.add_argument("--objects", type=int, nargs="+", default=None, help="object ids present (default: scene_gt.json)")
    p.add_argument("--out", type=Path, default=Path("results.csv"),
                   help="results CSV, written after every frame (default results.csv)")
    p.add_argument("--force", action="store_true", help="replace --out even if it is not a results CSV of ours")
    p.add_argument("--resume", action="store_true",
                   help="keep the frames already in --out and track the rest (the first one after a kept frame is "
                        "estimated from scratch)")
    p.add_argument("--posterior", type=Path, default=None, metavar="FILE.json",
                   help="also write each object's modes per frame as JSON (as estimate --posterior)")
    p.add_argument("--motion", choices=("auto", "given", "depth"), default="auto",
                   help="the camera's motion between frames: given (the scene's scene_camera_world.json), depth "
                        "(registered from the depth), auto (given where the scene has the file; default)")
    p.add_argument("--track-particles", type=int, default=TRACK_DEFAULTS.particles,
                   help=f"particles of a tracked frame (default {TRACK_DEFAULTS.particles}; at least "
                        f"{TRACK_DEFAULTS.lost_particles} where it re-searches lost objects)")
    p.add_argument("--track-iterations", type=int, default=TRACK_DEFAULTS.iterations,
                   help=f"iterations of a tracked frame (default {TRACK_DEFAULTS.iterations})")
    _add_estimator_args(p)  # the first frame's, and a re-initialised frame's: as estimate's
    _add_engine_args(p, "sequences one after another")
    p.add_argument("--max-retries", type=int, default=3,
                   help="times a dead worker is started again: --engine local, per batch (its part retried); "
                        "--engine ray, per sequence (tracked again from its first frame; default 3)")
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("label", help="pre-label a sequence: track it, fit every still object to all frames, check "
                                     "each frame against its depth, write BOP labels with the flagged frames")
    p.add_argument("dataset", type=Path, help="BOP dataset folder (root or split folder)")
    p.add_argument("--split", default=None, help="split folder (default: test, or the only one)")
    p.add_argument("--scene", type=int, required=True, help="scene id: the sequence to label")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="image ids A to B, both included, every one present (default: all of the scene's)")
    p.add_argument("--objects", type=int, nargs="+", default=None,
                   help="object ids present (default: the first frame's scene_gt.json)")
    p.add_argument("--out-labels", type=Path, default=None, metavar="FILE",
                   help="the labels, in scene_gt.json form (default: scene_gt_labels.json in the scene's folder); "
                        "FILE_info.json and FILE_provenance.json beside it")
    p.add_argument("--overwrite-gt", action="store_true",
                   help="write the scene's own scene_gt.json and scene_gt_info.json (backups kept)")
    p.add_argument("--fit-frames", type=int, default=LABEL_DEFAULTS.fit_frames,
                   help=f"frames, spread over the sequence, each still object is fitted to at once (0: none; "
                        f"default {LABEL_DEFAULTS.fit_frames})")
    p.add_argument("--snap", action="store_true",
                   help="put the fitted labels at rest with physics, then fit them to the depth again within the "
                        "settling region (default: as fitted; physics says how far it would move each)")
    p.add_argument("--end", nargs="+", default=None, metavar="OBJ:FRAME",
                   help="object OBJ's label ends at FRAME (taken out after it)")
    p.add_argument("--motion", choices=("auto", "given", "depth"), default="auto",
                   help="the camera's motion between frames, as track's (default auto)")
    _add_estimator_args(p)
    p.set_defaults(func=_cmd_label)

    p = sub.add_parser("score", help="score a BOP results CSV against the dataset's scene_gt.json")
    p.add_argument("dataset", type=Path, help="BOP dataset folder (root or split folder)")
    p.add_argument("results", type=Path, help="BOP results CSV (e.g. from `workbench estimate`)")
    p.add_argument("--split", default=None, help="split folder (default: test, or the only one)")
    p.add_argument("--json", type=Path, default=None, help="also write every object's errors to this JSON file")
    p.add_argument("--force", action="store_true", help="replace --json even if it is not a score JSON of ours")
    p.add_argument("--reliability", type=Path, default=None, metavar="PNG",
                   help="draw the reliability diagram of each object's top mode (results with several rows per "
                        "object, scored by probability: estimate's posterior)")
    p.set_defaults(func=_cmd_score)

    p = sub.add_parser("serve", help="the browser workbench")
    p.add_argument("dataset", type=Path, nargs="?")
    p.add_argument("--demo", action="store_true", help="serve the bundled demo scene")
    p.add_argument("--scene", type=int, default=None)
    p.add_argument("--frame", type=int, default=None)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--session", type=Path, default=None,
                   help="continue a saved session (its .json file); bit for bit with the same worker count (2)")
    p.add_argument("--sessions-dir", type=Path, default=None,
                   help="where sessions are saved and listed (default: the --session's folder, else ./sessions)")
    # The initial run (the panel changes them later); defaults: the app's DEFAULT_CONFIG.
    p.add_argument("--method", choices=("pipf", "mcpf"), default=None, help="estimator of the initial run (pipf)")
    p.add_argument("--particles", type=int, default=None, help="particles of the initial run (128)")
    p.add_argument("--iterations", type=int, default=None, help="iteration budget Run stops at (60)")
    _add_budget_arg(p, "a Run")
    _add_physics_arg(p, default=None)  # None: not given, so that a session's own is not silently overridden
    _add_engine_args(p, "particle batches on 2 worker processes")
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("make-scenes", help="generate a BOP dataset of scene categories")
    p.add_argument("out", type=Path)
    p.add_argument("--categories", default="touching,stacked,slant,occluded,three,four",
                   help="comma-separated, of touching,stacked,slant,occluded,three,four (the paper's); clutter, "
                   "mixed (larger desks, round objects, distractors, frames without the table pose); handle_hidden, "
                   "handle_shown (a mug whose handle the body hides from the camera, or that shows it); lying "
                   "(2-4 objects free, each in any stable pose: a can on its side, a bottle lying down); with "
                   "--models only: ycb_clutter (6-8 models, some touching, other models as distractors), raised (2-4 "
                   "on a large box on the table), leaning (a box leaning on a bowl or box), tools (drill, clamps, "
                   "scissors lying with 1-3 others)")
    p.add_argument("--models", type=Path, default=None, metavar="DIR",
                   help="draw the objects from this BOP dataset's (or models folder's) models, e.g. the YCB-Video "
                   "models, instead of the built-in ones (category lying; ycb_clutter, raised, leaning and tools "
                   "need it); they are copied into OUT")
    p.add_argument("--distractors", type=int, default=None,
                   help="objects the estimator is not told about, per scene (default: clutter 2-4, mixed 1-3, else 0)")
    p.add_argument("--table-pose", type=float, default=None, metavar="P",
                   help="share of frames whose scene_camera.json gives the table pose (default: 1; clutter 0.5, "
                   "mixed 0)")
    p.add_argument("--per-category", type=int, default=7)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sequence", type=int, default=None, metavar="N",
                   help="each scene as a sequence of N frames, the camera on an arc about the objects, its pose per "
                   "frame in scene_camera_world.json (as the real sequences; for `workbench track`)")
    p.add_argument("--arc", type=float, default=10.0, help="with --sequence: the camera's arc, degrees (default 10)")
    p.add_argument("--push", type=int, default=None, metavar="K",
                   help="with --sequence: from frame K (0-based) on, one object standing on the table is pushed away "
                   "from the others")
    p.add_argument("--push-distance", type=float, default=0.05, metavar="M", help="how far, metres (default 0.05)")
    p.add_argument("--take-out", default=None, metavar="K:J",
                   help="with --sequence: on frames K to J-1 one object standing on the table is out of the scene "
                   "(lifted away: not in the depth nor in scene_gt.json), from J on back where it was (K: never back)")
    p.add_argument("--handle", type=int, default=None, metavar="K",
                   help="with --sequence and --categories handle_hidden: the mug's handle, hidden behind its body on "
                   "the first frames, comes into view from frame K on as the camera moves (the arc is chosen for "
                   "it; --arc is not used)")
    p.add_argument("--sensor", choices=SENSOR_NAMES, default=DEFAULT_SENSOR,
                   help="the depth sensor's model: xtion (the default: measured on the real YCB-Video frames, "
                   "correlated noise and distortion growing with z^2, holes at edges and grazing angles, flying "
                   "pixels), kinect-like (white noise growing with depth, 1 mm steps, holes at edges; the sets of "
                   "the benchmarks' figures before 2026-12-07) or ideal (the exact depth)")
    p.add_argument("--demo", action="store_true", help="write the small bundled demo (assets/demo) instead")
    p.add_argument("--force", action="store_true", help="write into OUT even if it is not empty")
    p.set_defaults(func=_cmd_make_scenes)

    p = sub.add_parser("bench", help="Tables I and II (accuracy, convergence) or --speed")
    p.add_argument("dataset", type=Path, nargs="?")
    p.add_argument("--speed", action="store_true",
                   help="particle evaluations per second and peak memory, on DATASET or generated frames")
    p.add_argument("--quick", action="store_true", help="few scenes, small budget (CI)")
    p.add_argument("--methods", default="icp,pipf,mcpf")
    p.add_argument("--proposals", choices=PROPOSALS, default="default", help="the filters' search (default|paper)")
    p.add_argument("--particles", type=int, default=None, help="override the per-object-count default budget")
    p.add_argument("--iterations", type=int, default=None, help="override the maximum iterations")
    p.add_argument("--state", choices=("auto", *STATES), default="auto",
                   help="auto: 6-DoF for 2 objects, the paper's x,y,z,yaw for 3-4 (default)")
    p.add_argument("--categories", default=None, help="comma-separated subset of the dataset's categories")
    p.add_argument("--per-category", type=int, default=None, help="only the first N scenes of each category")
    p.add_argument("--no-early-stop", action="store_true", help="run every iteration even after convergence")
    p.add_argument("--workers", type=int, default=2)
    _add_engine_args(p, "frames one after another (not with --speed)")
    p.add_argument("--max-retries", type=int, default=3,
                   help="times a dead worker is started again: --engine local, per batch (its part retried); "
                        "--engine ray, per frame (default 3)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("bench-out"))
    p.add_argument("--profile", action="store_true",
                   help="where one frame's time goes (--scene S --frame F of DATASET): wall seconds and evaluations "
                        "per stage of the search, the workers' physics, rendering and likelihood")
    p.add_argument("--scene", type=int, default=None, help="with --profile: the frame's scene id")
    p.add_argument("--frame", type=int, default=None, help="with --profile: the frame's image id")
    p.add_argument("--tracked-from", type=int, default=None, metavar="A",
                   help="with --profile: track the scene from image A (estimated from scratch) to --frame, as "
                        "`track` does, and profile that tracked frame")
    p.add_argument("--png", type=Path, default=None, help="with --profile: also draw it as a stacked bar (PNG)")
    p.add_argument("--force", action="store_true", help="with --png: replace a file that is not a PNG")
    _add_budget_arg(p, "with --profile: the frame")
    _add_physics_arg(p)
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s: %(message)s")
    previous = _stop_on_sigterm()
    _TERMINATED.clear()
    try:
        code = args.func(args)
        if _TERMINATED.is_set():  # a command that stops on Ctrl-C as its way to end (serve) was stopped by SIGTERM
            raise _Terminated()
        return code
    except InputError as err:
        print(f"workbench: error: {err}", file=sys.stderr)
        return 2
    except _Terminated:
        print("workbench: stopped by SIGTERM; finished work is kept (estimate: in --out, continue with --resume)",
              file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


_TERMINATED = threading.Event()  # set by SIGTERM: the exit code is 143 even where a command took it as Ctrl-C


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the main process is, so that it stops as on Ctrl-C: workers told to stop, files whole."""


def _stop_on_sigterm():
    """SIGTERM -> ``_Terminated`` in the main thread -> the previous handler (None when this is not the main
    thread, where no handler can be set)."""
    def stop(signum, frame):
        _TERMINATED.set()
        raise _Terminated()

    try:
        return signal.signal(signal.SIGTERM, stop)
    except ValueError:  # not the main thread
        return None


if __name__ == "__main__":
    sys.exit(main())
