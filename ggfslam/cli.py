"""Command line: ``ggfslam run | live | demo | eval | render | view | synth | bench | batch | calibrate-depth |
config-help``."""
from __future__ import annotations

import contextlib
import functools
import shutil
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape

from ggfslam.errors import GGFSlamError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="ggfslam: RGB-D Gaussian-Splatting SLAM (GGF-SLAM) on CPU.")
console = Console()
err_console = Console(stderr=True)


def user_errors(fn):
    """Turn errors caused by user input into one line on stderr and exit code 2 (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except GGFSlamError as e:
            # escaped: a message may hold square brackets (pip extras, paths) that rich would take for markup
            err_console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            err_console.print("interrupted")
            raise typer.Exit(130) from None

    return wrapper


RENDERED_VIRTUAL_BASELINE = 0.5
"""``tracking.virtual_baseline`` for rendered sequences, whose depth is registered to the colour exactly: the demo's
and the benchmarks' (configs/synthetic and configs/replica write the same value; see ``TrackingConfig``)."""

DEMO_CONFIG = {
    "name": "demo",
    "dataset": {"kind": "synthetic",
                "synthetic": {"source": "procedural", "n_frames": 120, "width": 640, "height": 480,
                              "trajectory": "orbit", "seed": 0, "depth_noise": True}},
    "tracking": {"virtual_baseline": RENDERED_VIRTUAL_BASELINE},  # as configs/synthetic/default.yaml
}


def _print_result(metrics: dict, run_dir: Path, title: str) -> None:
    from ggfslam.eval.report import print_metrics

    print_metrics(metrics, title=title, console=console)
    console.print(f"run directory: {run_dir}")


@contextlib.contextmanager
def _live_viewer(view: bool, host: str, port: int):
    """With ``view``, a live viewer for the run (imported only then), kept serving after the run until Ctrl-C."""
    if not view:
        yield None
        return
    from ggfslam.viewer.app import viewer_address
    from ggfslam.viewer.live import LiveViewer

    viewer = LiveViewer(host, port)
    console.print(f"live viewer: {viewer_address(viewer.port, host)}", highlight=False, soft_wrap=True)
    try:
        yield viewer
        _serve_until_interrupted("the run is finished; the viewer shows its folder until Ctrl-C")
    finally:
        viewer.close()


@app.command()
@user_errors
def run(
    config: Optional[Path] = typer.Argument(None, help="YAML config file (see configs/), or a recorded sequence's "
                                            "folder (any layout `dataset.kind: auto` detects) to run with the built-in "
                                            "defaults; optional with --resume."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory to create (or to continue with --resume)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value: --set dataset.stride=2 (repeatable)."),
    overwrite: bool = typer.Option(False, help="Replace an existing run directory made by ggfslam."),
    resume: bool = typer.Option(False, "--resume", help="Continue an interrupted run from its checkpoint."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    view: bool = typer.Option(False, "--view", help="Serve the web viewer, updated live while the sequence runs."),
    port: int = typer.Option(8080, help="--view: port to serve on (0: any free one)."),
    host: str = typer.Option("127.0.0.1", help="--view: address to bind (default: this machine only)."),
):
    """Run SLAM on a configured sequence (or a sequence's folder, with the built-in defaults) and write a run
    directory."""
    from ggfslam.config import folder_config, load_config
    from ggfslam.rundir import CONFIG_FILE, require_run_dir

    if config is None:
        if not resume:
            raise typer.BadParameter("a config file is required (or --resume to continue a run)", param_hint="CONFIG")
        config = require_run_dir(out) / CONFIG_FILE
    if resume and overwrite:
        raise typer.BadParameter("--resume and --overwrite exclude each other")
    # before the heavy imports: a bad config fails in a blink
    cfg = folder_config(config, set_) if config.is_dir() else load_config(config, set_)
    from ggfslam import slam

    _note_compile(cfg)
    with _live_viewer(view, host, port) as viewer:
        metrics = slam.run(cfg, out, overwrite=overwrite, progress=not no_progress, resume=resume, observer=viewer)
        _print_result(metrics, out, f"{cfg.name}: {metrics['sequence']['dataset']}")


# what a live run changes in the defaults (the config file and --set still win): the map must be made in the 60 s
# after the input, at 320 px with 5 children per anchor (7-Scenes kitchen at 30 Hz: 25.35 dB against 24.73 with
# 10 children and 23.08 dB at 640 px; benchmarks/bench_live.py)
LIVE_DEFAULTS = ["mapping.train_width=320", "mapping.n_offsets=5", "mapping.final_seconds=60"]


def _live_source(source: str, out: Path, rate: float, queue: int, preload: Optional[bool], fps: float,
                 width: int, height: int, idle_timeout: float):
    """(the source's config overrides, a factory of the source from the loaded config)."""
    kind, colon, arg = source.partition(":")
    if kind not in ("replay", "realsense", "folder") or (colon and not arg) or (kind == "folder" and not arg):
        raise typer.BadParameter(f"{source!r}: expected replay[:PATH], realsense[:SERIAL or recording .bag/.db3] "
                                 "or folder:PATH", param_hint="--source")
    if queue not in (1, 2):
        raise typer.BadParameter(f"{queue}: a queue of 1 or 2 frames", param_hint="--queue")
    if kind == "replay":
        from ggfslam.sources.replay import ReplaySource

        def replay(cfg):
            from ggfslam.data.sources import open_dataset_from_config

            return ReplaySource(open_dataset_from_config(cfg.dataset), rate, queue, preload)

        return ([f"dataset.path={arg}", "dataset.kind=auto"] if arg else []), replay
    # the source names the sequence: the config's dataset section is replaced (its path only has to be valid)
    if kind == "folder":
        from ggfslam.sources.folder import FolderSource

        return [f"dataset.path={arg}", "dataset.kind=folder"], \
            lambda cfg: FolderSource(arg, fps, idle_timeout, capacity=queue)
    from ggfslam.sources.realsense import RECORDING_SUFFIXES, RealSenseSource

    recording = arg if arg.lower().endswith(RECORDING_SUFFIXES) else None
    serial = arg if arg and recording is None else None
    return [f"dataset.path={out / 'input'}", "dataset.kind=tum"], \
        lambda cfg: RealSenseSource(serial, recording, width, height, int(fps), capacity=queue)


@app.command()
@user_errors
def live(
    config: Optional[Path] = typer.Argument(None, help="YAML config file (default: the built-in settings)."),
    source: str = typer.Option(..., "--source", help="replay (the config's sequence) or replay:PATH (any dataset "
                               "folder ggfslam reads), delivered at its timestamps' pace; realsense, "
                               "realsense:SERIAL or realsense:RECORDING.bag|.db3 (pip install 'ggfslam[realsense]'); "
                               "folder:PATH, a folder another program fills (rgb/, depth/, camera.yaml)."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory to create."),
    rate: float = typer.Option(1.0, help="replay: speed, 1.0 = the timestamps' own pace, 0.25 = four times slower."),
    queue: int = typer.Option(2, help="Frames waiting for the system at most (1 or 2); older ones are dropped."),
    preload: Optional[bool] = typer.Option(None, "--preload/--no-preload", help="replay: decode every frame before "
                                           "the replay starts, as a sensor driver hands over decoded frames "
                                           "(default: when they fit in 4 GiB)."),
    fps: float = typer.Option(30.0, help="realsense: frame rate to stream; folder: frames per second of the "
                                         "timestamps (index / fps)."),
    width: int = typer.Option(640, help="realsense: width of the colour and depth streams."),
    height: int = typer.Option(480, help="realsense: height of the colour and depth streams."),
    idle_timeout: float = typer.Option(0.0, "--idle-timeout", help="folder: end the input after this many "
                                                                   "seconds without a new frame (0: at Ctrl-C)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value (repeatable)."),
    overwrite: bool = typer.Option(False, help="Replace an existing run directory made by ggfslam."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    view: bool = typer.Option(False, "--view", help="Serve the web viewer, updated live."),
    port: int = typer.Option(8080, help="--view: port to serve on (0: any free one)."),
    host: str = typer.Option("127.0.0.1", help="--view: address to bind (default: this machine only)."),
):
    """Run on frames delivered live: a RealSense camera, a folder being filled, or a replay on time; frames that
    arrive while the system is busy are dropped. Bundle adjustment and mapping run beside tracking; unless the
    config or --set says otherwise the map trains at 320 px width with 5 children per anchor, and for 60 s after the
    input ends (mapping.train_width, n_offsets, final_seconds). Ctrl-C ends the input and the run finishes (outputs written, exit status 0); a second
    Ctrl-C stops at once."""
    from ggfslam.config import apply_overrides, config_from_dict, load_config

    pre, make_source = _live_source(source, out, rate, queue, preload, fps, width, height, idle_timeout)
    # bundle adjustment and mapping run beside tracking (sequential ones would stall the input at every keyframe)
    pre += ["backend.concurrent=true", "mapping.concurrent=true", "mapping.realtime=true"]
    cfg = (load_config(config, pre + set_, defaults=LIVE_DEFAULTS) if config is not None
           else config_from_dict(apply_overrides({"name": "live"}, LIVE_DEFAULTS + pre + set_), "live"))
    from ggfslam import slam

    _note_compile(cfg)
    with _live_viewer(view, host, port) as viewer:
        metrics = slam.run(cfg, out, overwrite=overwrite, progress=not no_progress, observer=viewer,
                           live=make_source(cfg))
        _print_result(metrics, out, f"{cfg.name} (live): {metrics['live']['source']}")


@app.command()
@user_errors
def demo(
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Run directory (default: runs/demo-<time>)."),
    frames: int = typer.Option(120, help="Number of synthetic frames."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value (repeatable)."),
    view: bool = typer.Option(False, "--view", help="Serve the web viewer, updated live while the sequence runs."),
    port: int = typer.Option(8080, help="--view: port to serve on (0: any free one)."),
    host: str = typer.Option("127.0.0.1", help="--view: address to bind (default: this machine only)."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar (logs, CI)."),
):
    """Generate the built-in synthetic sequence, run the whole pipeline on it and print the metrics."""
    import copy

    from ggfslam import slam
    from ggfslam.config import apply_overrides, config_from_dict

    data = copy.deepcopy(DEMO_CONFIG)
    data["dataset"]["synthetic"]["n_frames"] = frames
    cfg = config_from_dict(apply_overrides(data, set_), "demo")
    out = out or Path("runs") / f"demo-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
    _note_compile(cfg)
    with _live_viewer(view, host, port) as viewer:
        console.print("rendering the synthetic sequence (cached after the first time) ...")
        metrics = slam.run(cfg, out, observer=viewer, progress=not no_progress)
        _print_result(metrics, out, "ggfslam demo: synthetic room")


def _note_compile(cfg) -> None:
    """Say so when a run starts by compiling the kernels (a fresh install): a minute would pass in silence."""
    from ggfslam.kernel_warmup import kernels_compiled

    if cfg.mapping.enabled and not kernels_compiled():
        console.print("compiling the numba kernels on every core (once per install and machine) ...")


@app.command("compile-kernels")
def compile_kernels_cmd(jobs: Optional[int] = typer.Option(None, help="Processes (default: one per core).")):
    """Compile every numba kernel into the cache now, on every core (a run does this itself when it needs to):
    for a machine image or cluster nodes prepared before their first run."""
    from ggfslam.kernel_warmup import compile_kernels, kernels_compiled

    if kernels_compiled():
        console.print("the kernels are compiled already")
        return
    t0 = time.perf_counter()
    job = compile_kernels(jobs, background=True)
    ok = job.wait() if job is not None else kernels_compiled()  # None: compiled by another process, or jobs 0
    for part, (seconds, error) in ({} if job is None else job.results).items():
        console.print(f"  {part}: {seconds:.0f} s" + (f", failed: {error}" if error else ""), highlight=False)
    if not ok:
        if job is None:
            console.print("nothing compiled (--jobs 0)")
        raise typer.Exit(1)
    console.print(f"kernels compiled in {time.perf_counter() - t0:.0f} s", highlight=False)


@app.command("eval")
@user_errors
def eval_(run_dir: Path = typer.Argument(..., help="A run directory written by `ggfslam run`.")):
    """Recompute a run's metrics from its files and print the table."""
    from ggfslam.rundir import require_run_dir

    require_run_dir(run_dir)
    from ggfslam import slam

    metrics = slam.evaluate(run_dir)
    _print_result(metrics, run_dir, f"eval: {metrics.get('sequence', {}).get('dataset', run_dir)}")


@app.command()
@user_errors
def render(
    run_dir: Path = typer.Argument(..., help="A run directory written by `ggfslam run` (with mapping)."),
    frames: str = typer.Option("keyframes", help="'keyframes', 'all', or a slice start:stop[:step] of the sequence."),
    path: Optional[Path] = typer.Option(None, help="TUM trajectory (camera-to-world) to render instead of frames."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output folder (default RUN_DIR/renders)."),
    width: Optional[int] = typer.Option(None, help="Render width (default: the training width)."),
    overwrite: bool = typer.Option(False, help="Replace PNGs of an earlier render in the output folder."),
    ply: bool = typer.Option(False, "--ply", help="Render the baked gaussians.ply (what standard viewers show) instead "
                             "of the neural map (default output folder RUN_DIR/renders_ply)."),
):
    """Render frames of a run, or a new camera path, to PNGs (colour, 16-bit depth in mm)."""
    from ggfslam.render_run import render_run

    written = render_run(run_dir, frames=frames, path=path, out=out, width=width, overwrite=overwrite, ply=ply)
    console.print(f"wrote {written['count']} views to {written['folder']}")


@app.command()
@user_errors
def view(
    run_dir: Path = typer.Argument(..., help="A run directory written by `ggfslam run` (finished or stopped)."),
    port: int = typer.Option(8080, help="Port to serve on (0: any free one)."),
    host: str = typer.Option("127.0.0.1", help="Address to bind; the default is this machine only (use SSH "
                             "port forwarding), 0.0.0.0 serves every network."),
    max_splats: int = typer.Option(1_000_000, help="Show at most this many Gaussians (the most opaque)."),
):
    """Serve a web viewer of a run: the Gaussian map, mesh, trajectories and factor graph (Ctrl-C stops it)."""
    from ggfslam.viewer.app import serve_run, viewer_address

    server, scene = serve_run(run_dir, host=host, port=port, max_splats=max_splats)
    for layer, why in scene.layers.problems.items():
        err_console.print(f"[yellow]{layer}:[/yellow] {why}", highlight=False, soft_wrap=True)
    try:
        _serve_until_interrupted(f"viewer of {scene.layers.run_dir}: {viewer_address(server.get_port(), host)}")
    finally:
        server.stop()


def _serve_until_interrupted(message: str) -> None:
    """Print ``message`` and block until Ctrl-C, which ends serving normally (exit status 0); the message is
    printed inside, so a Ctrl-C answering it at once is caught too."""
    try:
        console.print(message, highlight=False, soft_wrap=True)
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        console.print("viewer stopped")


@app.command()
@user_errors
def synth(
    out: Path = typer.Argument(..., help="Folder to write the sequence into (TUM layout + camera.yaml + mesh.ply)."),
    source: str = typer.Option("procedural", help="procedural | replica | mesh"),
    frames: int = typer.Option(120, help="Number of frames."),
    width: int = typer.Option(640),
    height: int = typer.Option(480),
    trajectory: str = typer.Option("orbit", help="Procedural camera path: orbit | loop | line."),
    seed: int = typer.Option(0),
    depth_noise: bool = typer.Option(False, "--depth-noise", help="Kinect-like depth noise."),
    textureless_wall: bool = typer.Option(False, "--textureless-wall"),
    replica_root: str = typer.Option("${GGFSLAM_DATA}/replica_office0_mini", help="Replica folder (source replica)."),
    stride: int = typer.Option(1, help="Pose stride (source replica)."),
    mesh: Optional[str] = typer.Option(None, help="Mesh with vertex colours (source mesh)."),
    poses: Optional[str] = typer.Option(None, help="TUM trajectory to render along (source mesh)."),
    camera_yaml: Optional[Path] = typer.Option(None, help="camera.yaml with intrinsics (source mesh)."),
    overwrite: bool = typer.Option(False, help="Replace a sequence ggfslam wrote there before."),
):
    """Render a synthetic RGB-D sequence with ground truth to disk."""
    from ggfslam.config import SyntheticConfig, config_from_dict
    from ggfslam.data.sources import generate_synthetic
    from ggfslam.errors import RunDirError

    syn = config_from_dict({"dataset": {"kind": "synthetic", "synthetic": {
        "source": source, "n_frames": frames, "width": width, "height": height, "trajectory": trajectory,
        "seed": seed, "depth_noise": depth_noise, "textureless_wall": textureless_wall,
        "replica_root": replica_root, "stride": stride, "mesh_path": mesh, "trajectory_path": poses}}},
        "command line").dataset.synthetic
    assert isinstance(syn, SyntheticConfig)
    camera = None
    if camera_yaml is not None:
        from ggfslam.data.camera_file import read_camera_yaml

        camera = read_camera_yaml(camera_yaml)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise RunDirError(f"{out}: folder exists and is not empty; pass --overwrite or choose another folder")
        if not (out / "camera.yaml").is_file():
            raise RunDirError(f"{out}: not a sequence written by ggfslam; refusing to delete it")
        shutil.rmtree(out)
    path = generate_synthetic(syn, camera, out_dir=out)
    console.print(f"wrote {frames} frames to {path}")


@app.command()
@user_errors
def bench(
    configs: list[Path] = typer.Argument(..., help="Sequence config files (YAML), e.g. configs/tum/fr3_cabinet_kf.yaml."),
    out: Path = typer.Option(Path("runs/bench"), "--out", "-o",
                             help="Folder of the runs (<out>/<sequence>/<variant>); finished runs there are reused."),
    variants: str = typer.Option("base,ggf,ggf_gcgr", help="Comma list of variants: base, ggf, ggf_gcgr."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value in every run (repeatable)."),
    ray: str = typer.Option("local", "--ray", help="As for `ggfslam batch`: local, auto or HOST:PORT."),
    cpus: Optional[int] = typer.Option(None, "--cpus", help="--ray local: CPUs of the instance (default: all)."),
    num_cpus: float = typer.Option(2, "--num-cpus", help="CPUs (and threads) of each run (2: one run at a time on "
                                   "two cores, so frames/s compare across variants)."),
    retries: int = typer.Option(0, "--retries", help="Run a failed run again up to N times."),
    repeats: int = typer.Option(1, "--repeats", min=1, help="Runs of each variant (seeds 0 .. N-1); the table shows "
                                "mean ± standard deviation. A trajectory can move by centimetres under tiny "
                                "perturbations (fr3/cabinet: 1.9-3.1 cm), so one run is one draw."),
    keypoint_jitter: Optional[float] = typer.Option(
        None, "--keypoint-jitter", help="tracking.keypoint_jitter_px of every run (default: 0.001 px with "
        "--repeats > 1, else 0): what makes the seeds draw different trajectories."),
):
    """Ablation of the paper's Table 5: base / +GGF / +GGF+GCGR on each sequence, run as a batch plan."""
    from ggfslam.ablation import ablation_plan, format_table
    from ggfslam.batch import run_batch

    names = [v.strip() for v in variants.split(",") if v.strip()]
    plan = ablation_plan(configs, out, names, set_, num_cpus, repeats, keypoint_jitter)
    rows = run_batch(plan, out, ray=ray, retries=retries, cpus=cpus, console=console)
    _wide(console).print(format_table(rows))
    _report_failures(rows, out)


def _report_failures(rows: list[dict], out: Path) -> None:
    """Where the results are; exit status 1 when a run of the batch did not finish."""
    failed = sum(r["status"] != "finished" for r in rows)
    console.print(f"runs, results.csv and results.json in {out}" + (f"; {failed} run(s) failed" if failed else ""),
                  highlight=False, soft_wrap=True)
    if failed:
        raise typer.Exit(1)


def _wide(c: Console) -> Console:
    # piped into a log, rich would squeeze a table into 80 columns and cut the names
    return c if c.is_terminal else Console(width=170)


@app.command()
@user_errors
def batch(
    plan: Path = typer.Argument(..., help="Plan file (YAML): sequences, variants, sweeps, seeds; see configs/plans/."),
    out: Path = typer.Option(..., "--out", "-o", help="Batch folder: one run folder per run, results.csv/json."),
    ray: str = typer.Option("local", "--ray", help="local (a Ray instance on this machine), auto (the running "
                            "cluster) or HOST:PORT of a cluster's head."),
    cpus: Optional[int] = typer.Option(None, "--cpus", help="--ray local: CPUs of the instance (default: all)."),
    retries: int = typer.Option(0, "--retries", help="Run a failed run again up to N times (from its checkpoint)."),
):
    """Run every (sequence, variant, seed) of a plan as Ray tasks and gather the results into one table."""
    from ggfslam.batch import load_plan, results_table, run_batch

    p = load_plan(plan, out)  # a bad plan fails before Ray starts
    console.print(f"{p.name}: {len(p.runs)} runs into {out}", highlight=False, soft_wrap=True)
    rows = run_batch(p, out, ray=ray, retries=retries, cpus=cpus, console=console)
    _wide(console).print(results_table(rows, title=p.name))
    _report_failures(rows, out)


@app.command("calibrate-depth")
@user_errors
def calibrate_depth(
    config: Path = typer.Argument(..., help="Config of an unregistered sequence (its intrinsics: the depth camera's)."),
    frames: int = typer.Option(20, help="Frames to fit on, spread over the sequence."),
    baseline: float = typer.Option(-0.025, help="Starting x offset (m) of the depth camera in the colour camera."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value (repeatable)."),
):
    """Fit the depth camera's registration to the colour camera from the sequence (depth edges onto colour edges)
    and print the dataset.camera and dataset.depth_registration sections to paste into the config."""
    import yaml

    from ggfslam.config import load_config
    from ggfslam.data.depth_calibration import fit_depth_registration
    from ggfslam.data.sources import open_dataset_from_config
    from ggfslam.errors import ConfigError

    cfg = load_config(config, set_)
    if cfg.dataset.depth_registration is not None:
        raise ConfigError(f"{config}: dataset.depth_registration is already set; fit on the unregistered sequence")
    ds = open_dataset_from_config(cfg.dataset)
    if ds.raw_camera.distortion:
        # the fit holds the depth camera's pinhole intrinsics and moves a pinhole colour camera against them
        raise ConfigError(f"{config}: the camera has lens distortion {list(ds.raw_camera.distortion)}; calibrate-depth "
                          "fits pinhole cameras: set dataset.camera.distortion to [] (the depth camera's) and "
                          "undistort the colour images before fitting")
    cam = ds.camera
    fit = fit_depth_registration(ds, n_frames=frames, baseline_guess=baseline)
    # plain text, never re-wrapped: it is pasted into a config
    typer.echo(f"# depth edges to colour edges: {fit.distance_before_px:.2f} px as read, "
               f"{fit.distance_after_px:.2f} px registered ({fit.edge_points} edge pixels in {fit.frames} frames)")
    section = fit.as_config((cam.fx, cam.fy, cam.cx, cam.cy), cam.width, cam.height, cam.depth_scale)
    typer.echo(yaml.safe_dump({"dataset": section}, sort_keys=False, default_flow_style=None, width=1000))


@app.command("config-help")
def config_help():
    """List every configuration key with its default and meaning."""
    from rich.table import Table

    from ggfslam.config import describe_fields

    table = Table("key", "default", "meaning")
    for key, default, doc in describe_fields():
        table.add_row(key, default, doc)
    console.print(table)


def main() -> None:
    """Entry point of the ``ggfslam`` script."""
    app()


if __name__ == "__main__":
    sys.exit(main())
