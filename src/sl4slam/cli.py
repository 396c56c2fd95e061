"""Command-line interface: a thin layer over the library.

``sl4slam run SOURCE --out DIR`` runs the pipeline; ``sl4slam demo`` the synthetic SL(4)-vs-Sim(3)
comparison; ``sl4slam synth`` writes the synthetic world; ``sl4slam models`` lists the models;
``sl4slam convert`` converts any model's weights; ``sl4slam ate`` evaluates a trajectory; ``sl4slam view`` shows a result in the browser; ``sl4slam export``
writes it for COLMAP / nerfstudio / PLY tools; ``sl4slam eval`` / ``sl4slam sweep`` run the paper's
TUM RGB-D / 7-Scenes protocol. Run flags are generated from the config dataclasses
(``sl4slam.config``), so every setting, its default and its documentation live in one place.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

from . import __version__
from .config import SLAMConfig, config_from_dict, read_config_file
from .config import sections as sections_of
from .cli_help import HelpAll, ShortHelp, unknown_flags, unknown_flags_message
from .errors import UserError

log = logging.getLogger("sl4slam")

@functools.lru_cache(maxsize=None)
def _module_classes(filename: str) -> dict[str, ast.ClassDef]:
    """Every class definition of a source file by name, parsed once (``inspect.getsource`` parses
    the whole module again for each class: seconds for the CLI's dozens of config sections)."""
    tree = ast.parse(Path(filename).read_text(encoding="utf-8"))
    return {node.name: node for node in ast.walk(tree) if isinstance(node, ast.ClassDef)}


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after each field) of a dataclass."""
    try:
        node = _module_classes(inspect.getsourcefile(cls) or "").get(cls.__name__)
    except (OSError, TypeError, SyntaxError):
        return {}
    if node is None:
        return {}
    body = node.body
    docs = {}
    for node, following in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant) and isinstance(following.value.value, str):
                docs[node.target.id] = " ".join(following.value.value.split())
    return docs


def _scalar_type(value: Any):
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return int
    if isinstance(value, float):
        return float
    return str


def add_config_flags(parser: argparse.ArgumentParser, config: Any = None) -> None:
    """Add one flag per config field; values land in ``args`` as ``section.field`` destinations.

    Flag names, choices and the "advanced" grouping come from the sections themselves
    (``sl4slam.config.Section``); the help text is each field's docstring and default.
    """
    config = config if config is not None else SLAMConfig()
    sections: list[tuple[str, Any]] = [("", config)] + [(s.section, s) for s in sections_of(config)]
    advanced_groups = []
    for name, section in sections:
        title = f"[{name}] settings" if name else "run settings"
        group = parser.add_argument_group(title)
        advanced = None
        docs = field_docs(type(section))
        for f in dataclasses.fields(section):
            value = getattr(section, f.name)
            if dataclasses.is_dataclass(value):
                continue
            if f.name in section.advanced:
                if advanced is None:
                    advanced = parser.add_argument_group(f"[{name or 'run'}] advanced settings")
                    advanced_groups.append(advanced)
                target = advanced
            else:
                target = group
            if section.flag(f.name) in parser._option_string_actions:
                continue  # the verb's own flag of that name wins (eval's --workers: runs in parallel)
            dest = f"{name}.{f.name}" if name else f.name
            default = f"default: {value}" if value is not None else f"default: from the profile; exact: {section.field_default(f.name)}"
            help_text = (docs.get(f.name, "") + f" ({default})").strip().replace("%", "%%")
            kwargs: dict[str, Any] = {"dest": dest, "default": argparse.SUPPRESS, "help": help_text}
            typed = value if value is not None else section.field_default(f.name)
            if isinstance(typed, bool):
                kwargs["action"] = argparse.BooleanOptionalAction
            elif f.name in section.choices:
                kwargs["choices"] = list(section.choices[f.name])
            else:
                kwargs["type"] = _scalar_type(typed)
                kwargs["metavar"] = f.name.upper()
            target.add_argument(section.flag(f.name), *section.flag_aliases.get(f.name, ()), **kwargs)
    # advanced groups after the main ones, so `run --help` reads top-down
    parser._action_groups = [g for g in parser._action_groups if g not in advanced_groups] + advanced_groups


def config_from_args(args: argparse.Namespace) -> SLAMConfig:
    """Defaults, then ``--config FILE``, then explicit flags (``--sim-profile`` fills every simulator
    magnitude that neither the file nor a flag sets)."""
    values = read_config_file(args.config) if getattr(args, "config", None) else {}
    config = config_from_dict(values, SLAMConfig())
    for dest, value in vars(args).items():
        if "." in dest:
            section, name = dest.split(".", 1)
            setattr(getattr(config, section), name, value)
        elif dest in {f.name for f in dataclasses.fields(SLAMConfig)} and not dataclasses.is_dataclass(getattr(config, dest)):
            setattr(config, dest, value)  # top-level settings (a verb's own positional SOURCE is not one)
    return config


def _flag_of(dest: str) -> str:
    """The command-line flag of a ``section.field`` destination."""
    section, _, name = dest.rpartition(".")
    owner = SLAMConfig() if not section else getattr(SLAMConfig(), section)
    return owner.flag(name)


# ---------------------------------------------------------------------- verbs
def cmd_run(args: argparse.Namespace) -> int:
    from .runner import run_slam

    config = config_from_args(args)
    view = _viewer_settings(args) if args.view else None
    run_slam(args.source, args.out, config, replay_dir=args.replay, progress=not args.quiet, overwrite=args.overwrite,
             view=view, all_frames=args.all_frames, keep_viewer=view is not None, resume=args.resume)
    return 0


def _viewer_settings(args: argparse.Namespace):
    from .viewer.scene import ViewerSettings

    return ViewerSettings(host=args.host, port=args.port, point_budget=getattr(args, "point_budget", ViewerSettings.point_budget))


def cmd_view(args: argparse.Namespace) -> int:
    from .viewer import view_result

    view_result(args.result, _viewer_settings(args))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from .export import export_result

    options = {} if args.format == "ply" else {"max_points": args.max_points}
    if args.format != "ply":
        options["image_ext"] = "." + args.image_format
    if args.format == "colmap":
        options.update(binary=True, text=args.text)
    report = export_result(args.result, args.format, args.out, **options)
    print(report.line())
    return 0


def _add_viewer_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="interface the viewer binds; other than loopback exposes the map to the network")
    parser.add_argument("--port", type=int, default=8080, help="viewer port (the next free one when taken)")


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    run_demo(Path(args.out), frames=args.frames, perspective=args.perspective, progress=not args.quiet)
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from .synthetic import get_style, write_seven_scenes_sequence, write_synthetic_sequence
    from .synthetic.suite import SUITE_HEIGHT, SUITE_WIDTH, write_suite

    if args.list:
        _print_styles_and_suite()
        return 0
    if args.suite is not None:
        single = [flag for flag, value in (("--out", args.out), ("--style", args.style), ("--frames", args.frames),
                                           ("--seed", args.seed), ("--layout", args.layout)) if value is not None]
        if single:
            raise UserError(f"--suite writes the suite's own sequences and takes only --split, --width, --height and "
                            f"--overwrite; drop {', '.join(single)}")
        folders = write_suite(args.suite, width=_given(args.width, SUITE_WIDTH), height=_given(args.height, SUITE_HEIGHT),
                              split=args.split, overwrite=args.overwrite, report=print)
        print(f"{len(folders)} synthetic sequences in {args.suite} (real sequences are read from their own folders: "
              "sl4slam synth --list)")
        return 0
    if args.out is None:
        raise UserError("synth needs --out DIR (one sequence) or --suite ROOT (the whole suite)")
    if args.split is not None:
        raise UserError("--split chooses a half of --suite; give --suite ROOT with it")
    style = get_style(args.style) if args.style is not None else None
    frames = args.frames if args.frames is not None else (style.frames if style else 600)
    options = dict(num_frames=frames, width=_given(args.width, 320), height=_given(args.height, 240),
                   seed=_given(args.seed, 0), overwrite=args.overwrite, style=args.style)
    if args.layout == "7scenes":
        path = write_seven_scenes_sequence(args.out, **options)
        print(f"wrote {frames} frames to {path} (7-Scenes layout)")
        return 0
    path = write_synthetic_sequence(args.out, **options)
    print(f"wrote {frames} frames to {path} (contact sheet: {Path(path) / 'contact_sheet.png'})")
    return 0


def _given(value, default):
    """A flag's value, or ``default`` when it was not given."""
    return default if value is None else value


def _print_styles_and_suite() -> None:
    """``synth --list``: every style, then every sequence of the suite with its half."""
    from .synthetic.styles import STYLES, style_summary
    from .synthetic.suite import SPLIT_RULE, SUITE, SUITE_HEIGHT, SUITE_WIDTH

    print("styles (sl4slam synth --style NAME [--frames N] [--seed S]):")
    for style in STYLES.values():
        print(f"  {style_summary(style)}")
    print(f"\nsuite (sl4slam synth --suite ROOT, {SUITE_WIDTH}x{SUITE_HEIGHT}; split: {SPLIT_RULE}):")
    for sequence in SUITE:
        what = f"{sequence.frames} frames, seed {sequence.seed}" if not sequence.real else f"real: {sequence.folder}"
        print(f"  {sequence.name:28s} {sequence.split:9s} {what}")


def cmd_eval(args: argparse.Namespace) -> int:
    from .evaluation import EvalSettings, evaluate

    from .evaluation.protocol import SEEDED_SETTINGS

    fixed_seeds = [_flag_of(dest) for dest in SEEDED_SETTINGS if dest in vars(args)]
    if fixed_seeds:
        raise UserError(f"{' and '.join(fixed_seeds)} cannot be set here: run r uses seed r; choose the seeds with --runs")
    config = config_from_args(args)
    settings = EvalSettings(dataset=args.dataset, runs=args.runs, dense=not args.no_dense,
                            keep_keyframe_points=args.keep_keyframe_points)
    outcome = evaluate(
        args.root, args.out, settings=settings, config=config, grid=args.grid, sequences=args.sequences,
        workers=args.workers, threads=args.threads, ray=args.ray is not None, ray_address=args.ray or None,
        replay_dir=args.replay, progress=not args.quiet,
    )
    print(Path(outcome.files["tables"]).read_text())
    failed = sum(1 for r in outcome.results if r["status"] != "ok")
    print(f"{len(outcome.results)} run(s): {outcome.computed} computed, {outcome.reused} reused, {failed} failed; "
          f"{outcome.seconds:.1f} s. Tables {outcome.files['tables']}, runs {outcome.files['runs']}, "
          f"JSON {outcome.files['json']}, {len(outcome.files['figures'])} figure(s) in {Path(args.out) / 'figures'}")
    return 1 if failed else 0


def _add_eval_arguments(parser: argparse.ArgumentParser, grid_required: bool) -> None:
    parser.add_argument("root", help="dataset root: rgbd_dataset_freiburg1_* folders (tum) or <scene>/seq-01 folders (7scenes)")
    parser.add_argument("--dataset", required=True, choices=["tum", "7scenes"], help="benchmark layout and protocol")
    parser.add_argument("--out", required=True, help="output folder (runs, frontend caches, tables); an earlier evaluation there is resumed")
    parser.add_argument("--sequences", nargs="+", metavar="NAME",
                        help="sequences (desk, chess, ...) or folders under the root (default: the paper's, all present)")
    parser.add_argument("--runs", type=int, default=5, help="runs per sequence; run r uses seed r for sim.seed and alignment.seed")
    parser.add_argument("--grid", nargs="+", required=grid_required, metavar="SETTING=V1,V2",
                        help="sweep settings, e.g. submap.size=8,16,32 backend.kind=sl4,sim3 (their product; one table each)")
    parser.add_argument("--workers", type=int, help="parallel runs (default: one per core; one per GPU for model runs on GPUs)")
    parser.add_argument("--threads", type=int, help="torch / OpenCV / BLAS threads per run (default: cores / workers)")
    parser.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                        help="run on Ray: join the cluster at ADDRESS (or RAY_ADDRESS), else start a local instance")
    parser.add_argument("--replay", metavar="DIR", help="frontend_cache/ folder of an earlier evaluation to replay from")
    parser.add_argument("--no-dense", action="store_true", help="7-Scenes: skip the dense metrics (no Open3D needed)")
    parser.add_argument("--keep-keyframe-points", action="store_true",
                        help="keep each run's keyframes/ (per-keyframe dense data, about 0.2-0.3 MB each in the compact layout)")
    parser.add_argument("--config", help="TOML or JSON file of run settings (flags override it)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_config_flags(parser)
    parser.set_defaults(func=cmd_eval)


def cmd_convert(args: argparse.Namespace) -> int:
    from .models.checkpoint import weights_passed_as
    from .registry import frontend_entry
    from .resolve import model_of_weights

    with weights_passed_as("pass {it} to sl4slam convert"):
        if args.model:
            entry = frontend_entry(args.model)
        else:
            entry = model_of_weights(args.src)
            if entry is None:
                raise UserError(f"{args.src}: not a checkpoint of a known model (or not found); name it with --model "
                                "(sl4slam models lists them)")
        if entry.convert is None:
            raise UserError(f"{entry.name} has no weights to convert")
        dtype = "bf16" if args.bf16 else args.dtype
        entry.convert(args.src, args.dst, dtype)
    print(f"wrote {args.dst} ({entry.name}, {dtype})")
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    """Every model a run can name: parameters, licence, default weights and whether they are here."""
    from .models.hub import cached_locally
    from .registry import frontend_entries, object_model_entries

    rows = [("name", "parameters", "licence", "default weights", "here", "what it is")]
    for entry in frontend_entries():
        if entry.weights is None:
            rows.append((entry.name, "-", "-", "-", "-", entry.description))
            continue
        found = cached_locally(entry.weights.repo_id, entry.weights)
        count = entry.parameters or 0
        size = f"{count / 1e9:.2f} B" if count >= 1e9 else f"{count / 1e6:.1f} M" if count else "?"
        rows.append((entry.name, size,
                     entry.licence.split(" (")[0], entry.weights.repo_id, "yes" if found else "no", entry.description))
    for entry in object_model_entries():
        count = entry.parameters
        size = f"{count / 1e9:.2f} B" if count >= 1e9 else f"{count / 1e6:.1f} M"
        found = cached_locally(entry.weights.repo_id, entry.weights)
        rows.append((entry.name, size, entry.licence, entry.weights.repo_id, "yes" if found else "no",
                     f"{entry.description} ({entry.role})"))
    widths = [max(len(row[k]) for row in rows) for k in range(5)]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) + "  " + row[5])
    print("\nRun one with --model NAME (or --model FILE / hub id: its weights name the model). Weights not here are "
          "downloaded on first use; licences in full: README.md, Models.")
    print("pe-core-l14-336 and sam3 serve the object queries (run --objects, sl4slam query), not --model.")
    return 0


def cmd_ate(args: argparse.Namespace) -> int:
    from .io import read_tum_trajectory
    from .metrics import ate

    t_gt, T_gt = read_tum_trajectory(args.groundtruth)
    t_est, T_est = read_tum_trajectory(args.estimate)
    result = ate(t_est, T_est, t_gt, T_gt, max_time_diff=args.max_diff, correct_scale=not args.no_scale)
    scale = f"Sim(3) scale factor {result.scale:.4f}" if not args.no_scale else "SE(3), scale not corrected"
    print(f"ATE rmse {result.rmse:.6f} m  mean {result.mean:.6f} m  median {result.median:.6f} m  "
          f"max {result.max:.6f} m  ({result.num_poses} poses, {scale})")
    return 0


def query_models(model: str):
    """The embedder called ``model`` (the one that made the result's keyframe embeddings) and the
    text segmenter, for ``sl4slam query`` (``sl4slam.objects.query.default_models``; a test
    replaces this function)."""
    from .objects.query import default_models

    return default_models(model)


def cmd_query(args: argparse.Namespace) -> int:
    import json

    from .atomic import atomic_write_text
    from .objects.query import check_query, open_for_query, query_result

    check_query(args.text, args.top_k, args.threshold)  # every bad input before a model loads
    result, embeddings = open_for_query(args.result)
    embedder, segmenter = query_models(embeddings.model)
    answer = query_result(result, args.text, embedder, segmenter, top_k=args.top_k, threshold=args.threshold)
    print(answer.table())
    if args.json:
        atomic_write_text(Path(args.json), json.dumps(answer.to_json(points=args.points), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sl4slam", description="Dense SLAM from an uncalibrated monocular camera on SL(4).")
    parser.add_argument("--version", action="version", version=f"sl4slam {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details (fallbacks, rejected loops)")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")

    run = verbs.add_parser("run", help="run SLAM on an image folder, video, TUM or 7-Scenes sequence",
                           usage="sl4slam run SOURCE --out DIR [--config FILE] [settings]", add_help=False,
                           description="Every setting below can also be given in a TOML/JSON file (--config); "
                                       "flags override the file. Advanced settings are listed last.")
    run.add_argument("-h", "--help", action=ShortHelp, help="the run's options and the settings most runs touch")
    run.add_argument("--help-all", action=HelpAll,
                     help="every setting, or those whose flag or text contains WORD (e.g. --help-all ransac)")
    run.add_argument("source", help="image folder, video file, TUM RGB-D or 7-Scenes sequence folder, camera index "
                                    "(0, 1, ...) or stream URL (rtsp://, http://): the kind is detected")
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--config", help="TOML or JSON file of settings (flags override it)")
    run.add_argument("--replay", help="replay recorded frontend outputs from this folder instead of running the model")
    run.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out (its files are removed first)")
    run.add_argument("--resume", action="store_true",
                     help="continue the run in --out that was killed or interrupted, with the same SOURCE and settings: "
                          "the submaps whose model outputs it recorded are replayed without the model, and the outputs "
                          "equal those of a run that was never interrupted (a run records what this needs unless --no-resumable)")
    run.add_argument("--quiet", action="store_true", help="no progress output")
    run.add_argument("--view", action="store_true",
                     help="watch the map grow in the browser (needs sl4slam[viewer]); it stays open after the run until Ctrl-C")
    _add_viewer_flags(run)
    run.add_argument("--all-frames", action="store_true",
                     help="also localize every other frame against its nearest keyframe: trajectory_all.txt")
    add_config_flags(run)
    run.set_defaults(func=cmd_run)

    view = verbs.add_parser("view", help="show a result folder in the browser (needs sl4slam[viewer])")
    view.add_argument("result", help="the --out folder of a run")
    _add_viewer_flags(view)
    view.add_argument("--point-budget", type=int, default=1_000_000, help="most points sent to the browser")
    view.set_defaults(func=cmd_view)

    export = verbs.add_parser("export", help="export a result folder: COLMAP sparse model, nerfstudio, per-submap PLY")
    export.add_argument("result", help="the --out folder of a run")
    export.add_argument("--format", required=True, choices=["colmap", "nerfstudio", "ply"])
    export.add_argument("--out", help="output folder (default: RESULT/export_FORMAT)")
    export.add_argument("--max-points", type=int, default=1_000_000, help="points in the COLMAP / nerfstudio point cloud")
    export.add_argument("--text", action="store_true", help="COLMAP: also write the .txt model beside the .bin one")
    export.add_argument("--image-format", choices=["png", "jpg"], default="png",
                        help="keyframe images: png (lossless) or jpg (quality 95, several times faster to write)")
    export.set_defaults(func=cmd_export)

    demo = verbs.add_parser("demo", help="synthetic world: SL(4) versus Sim(3) under a projective distortion")
    demo.add_argument("--out", default="sl4slam_demo", help="output folder")
    demo.add_argument("--frames", type=int, default=600, help="frames of the synthetic world")
    demo.add_argument("--perspective", type=float, default=0.2, help="perspective distortion of the simulated frontend")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=cmd_demo)

    synth = verbs.add_parser("synth", help="render the synthetic RGB-D world as a TUM RGB-D or 7-Scenes sequence")
    synth.add_argument("--out", help="output folder (for an evaluation root: ROOT/NAME, or ROOT/SCENE/seq-01)")
    synth.add_argument("--style", metavar="NAME",
                       help="room, textures and camera motion (sl4slam synth --list; default: the original world's lap)")
    synth.add_argument("--suite", metavar="ROOT", help="write every synthetic sequence of the suite as ROOT/NAME (256x192)")
    synth.add_argument("--split", metavar="HALF", help="with --suite: only the tune or the validate half")
    synth.add_argument("--list", action="store_true", help="list the styles and the suite's sequences with their half")
    synth.add_argument("--layout", choices=["tum", "7scenes"], default=None,
                       help="tum (default): rgb.txt, depth.txt, groundtruth.txt; 7scenes: frame-XXXXXX.{color,depth}.png, .pose.txt")
    synth.add_argument("--frames", type=int, default=None, help="frames (default: 600, or the style's length)")
    synth.add_argument("--width", type=int, default=None, help="image width (default: 320; the suite's: 256)")
    synth.add_argument("--height", type=int, default=None, help="image height (default: 240; the suite's: 192)")
    synth.add_argument("--seed", type=int, default=None, help="world and path seed (default 0)")
    synth.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    synth.set_defaults(func=cmd_synth)

    evaluation = verbs.add_parser("eval", help="evaluate on TUM RGB-D or 7-Scenes with the paper's protocol (tables, CSV, JSON, figures)",
                                  formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _add_eval_arguments(evaluation, grid_required=False)
    sweep = verbs.add_parser("sweep", help="eval over a grid of settings x seeds (--grid), locally in parallel or on Ray",
                             formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _add_eval_arguments(sweep, grid_required=True)

    models = verbs.add_parser("models", help="list the models: parameters, licence, default weights, whether they are here")
    models.set_defaults(func=cmd_models)

    convert = verbs.add_parser("convert", help="write a .safetensors copy of a model's checkpoint (any model)")
    convert.add_argument("src", help="checkpoint (.pt or .safetensors) or hub id")
    convert.add_argument("dst", help="output .safetensors")
    convert.add_argument("--model", help="the checkpoint's model (default: recognized from its tensor names)")
    convert.add_argument("--dtype", choices=["fp32", "bf16", "fp16"], default="fp32", help="storage precision")
    convert.add_argument("--bf16", action="store_true", help="same as --dtype bf16")
    convert.set_defaults(func=cmd_convert)

    ate_parser = verbs.add_parser("ate", help="ATE RMSE of a TUM trajectory (evo_ape -as)")
    ate_parser.add_argument("groundtruth")
    ate_parser.add_argument("estimate")
    ate_parser.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance (s)")
    ate_parser.add_argument("--no-scale", action="store_true", help="SE(3) instead of Sim(3) alignment")
    ate_parser.set_defaults(func=cmd_ate)

    query = verbs.add_parser("query", help="find an object in a result's map by text (needs a run with --objects)")
    query.add_argument("result", help="the --out folder of a run made with --objects")
    query.add_argument("text", help='what to find, for example "red mug"')
    query.add_argument("--top-k", type=int, default=5, help="keyframes searched: the most similar to the text")
    query.add_argument("--threshold", type=float, default=0.5, help="lowest mask score kept (0 to 1)")
    query.add_argument("--json", metavar="FILE", help="also write the answer as JSON (boxes in the map's frame and units)")
    query.add_argument("--points", action="store_true", help="with --json: include each instance's points")
    query.set_defaults(func=cmd_query)
    return parser


def _verb_parsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Each verb's parser by name."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    verbs = _verb_parsers(parser)
    named = next((i for i, token in enumerate(argv) if token in verbs), None)
    if named is not None:  # a mistyped flag: the verb's own usage and the closest names, before anything else
        unknown = unknown_flags(verbs[argv[named]], argv[named + 1:])
        if unknown:
            verbs[argv[named]].error(unknown_flags_message(verbs[argv[named]], unknown))
    args, extras = parser.parse_known_args(argv)
    if extras:
        verb = verbs.get(getattr(args, "verb", None), parser)
        verb.error(unknown_flags_message(verb, extras))
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s: %(message)s")
    from .runner import RunInterrupted

    try:
        return int(args.func(args) or 0)
    except RunInterrupted as exc:
        print(f"\nsl4slam: {exc}", file=sys.stderr)
        return exc.exit_code
    except UserError as exc:
        print(f"\nsl4slam: error: {exc}", file=sys.stderr)  # on its own line, whatever was printed before
        return 2
    except KeyboardInterrupt:
        print("\nsl4slam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
