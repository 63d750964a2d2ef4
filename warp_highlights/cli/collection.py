"""``warp-highlights collection``: fit, score and publish many captures on a Dask cluster."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..model.config import RESIDUAL_KINDS
from ..model.errors import InputError
from .args import Command, exposure_option, in_range, size_option

__all__ = ["COMMANDS", "EXIT_SOME_FAILED"]

EXIT_SOME_FAILED = 1
"""Exit status when some captures failed (each is named on stderr and in the gallery); the others are finished."""


def _collection_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("captures", type=Path, nargs="+",
                        help="capture folders (a .lp light file and its images), or folders searched for them")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output folder: index.html (the gallery), collection.json, and one folder per "
                             "capture (field.whf, "
                        "evaluation/, viewer/, thumbnail.png, capture.json)")
    group = parser.add_argument_group("passed to every fit")
    group.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.NAME=VALUE",
                       help="override a hyper-parameter, as fit --set (repeatable)")
    group.add_argument("--size", type=size_option("working size"),
                       help="working resolution WIDTHxHEIGHT, as fit --size (captures of one aspect ratio)")
    group.add_argument("--max-side", type=in_range(int, 8, 65_536), metavar="PX",
                       help="fit each capture at most PX pixels on its longer side, its aspect ratio kept (its fit "
                            "--size worked out from its "
                       "images; for captures of different sizes)")
    group.add_argument("--residual", choices=list(RESIDUAL_KINDS),
                       help="as fit --residual (default: fit's auto)")
    group.add_argument("--diffuse", choices=["lambert", "images", "none"], help="as fit --diffuse")
    group.add_argument("--exposure", type=exposure_option, help="as fit --exposure")
    group.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB (fit and evaluate)")
    group.add_argument("--max-megapixels", type=in_range(float, 0.001, 100_000.0), metavar="MP",
                       help="as fit --max-megapixels (fit and evaluate)")
    group = parser.add_argument_group("what each capture gets")
    group.add_argument("--holdout-every", type=in_range(int, 2, 1000), default=5, metavar="K",
                       help="a capture without held-out lights (no Test/ folder or heldout.lp) is scored by a second "
                            "fit without lights 0, K, "
                       "2K, ...; its published field keeps every light (default 5)")
    group.add_argument("--baselines", default="ptm,hsh2,hsh3,rbf",
                       help="as evaluate --baselines (default ptm,hsh2,hsh3,rbf; 'none')")
    group.add_argument("--no-evaluate", action="store_true", help="no scores: one fit per capture")
    group.add_argument("--no-export", action="store_true", help="no web viewer")
    group.add_argument(
        "--force", action="store_true",
        help="redo every capture (default: skip those finished, or failed, with the same options and files)")
    group.add_argument("--retry-failed", action="store_true",
                       help="try again the captures that failed before, although nothing changed")
    group = parser.add_argument_group("where it runs")
    group.add_argument("--scheduler", metavar="ADDRESS",
                       help="a running Dask scheduler (e.g. tcp://10.0.0.5:8786; dask-jobqueue, Kubernetes and the "
                            "like start one); its "
                       "workers must see the captures and OUTPUT at the same paths (default: a local cluster "
                       "on this machine)")
    group.add_argument("--workers", type=in_range(int, 1, 1024),
                       help="local workers (default: one per GPU, else one per 4 CPU cores)")
    group.add_argument("--gpus", type=in_range(int, 0, 1024),
                       help="GPUs of this machine to use, one worker each (default: every visible one; 0: CPU workers)")
    group.add_argument("--device", help="--device for every command, e.g. cpu (default: the worker's GPU)")


def _run_collection(args) -> int:
    from ..collection.job import JobOptions
    from ..collection.runner import run
    from ..model.config import FitSettings

    FitSettings().with_overrides(list(args.overrides))  # a wrong --set is one line now, not one per capture
    if args.size is not None and args.max_side is not None:
        raise InputError("give --size (one size for every capture) or --max-side (each capture's own), not both")
    fit_args: list[str] = []
    for override in args.overrides:
        fit_args += ["--set", override]
    if args.size is not None:
        fit_args += ["--size", f"{args.size[0]}x{args.size[1]}"]
    for option, value in (("--residual", args.residual), ("--diffuse", args.diffuse), ("--exposure", args.exposure)):
        if value is not None:
            fit_args += [option, str(value)]
    options = JobOptions(fit_args=tuple(fit_args), holdout_every=args.holdout_every, evaluate=not args.no_evaluate,
                         export=not args.no_export,
                         baselines=_baselines(args.baselines), linear=args.linear, max_megapixels=args.max_megapixels,
                         max_side=args.max_side)
    result = run(args.captures, args.output, options=options, force=args.force, retry_failed=args.retry_failed,
                 scheduler=args.scheduler,
                 workers=args.workers, gpus=args.gpus, device=args.device, progress=not args.quiet)
    failed = result.failed + result.failed_before
    print(f"wrote {result.output / 'index.html'}: {len(result.processed)} captures done now, {len(result.skipped)} "
          f"finished before, "
          f"{len(failed)} failed" + (f" ({', '.join(failed)})" if failed else ""))
    if result.failed_before:
        print(f"not tried again (nothing changed since they failed; --retry-failed tries them): "
              f"{', '.join(result.failed_before)}")
    if result.processed or result.skipped:
        print(f"browse it with: warp-highlights serve {result.output}")
    return EXIT_SOME_FAILED if failed else 0


def _baselines(text: str) -> str:
    from .relight import parse_baselines

    names = parse_baselines(text)
    return ",".join(names) if names else "none"


COMMANDS = (
    Command("collection", _collection_arguments, _run_collection,
            help="fit, score and export many captures on a Dask cluster (one GPU per worker), "
                 "resumable, with a gallery",
            description="For each capture: fit (passing on the fit options), evaluate at held-out lights (a Test/ "
                        "folder or heldout.lp, "
            "else every K-th light held out by a second fit), export the web viewer and a thumbnail, into "
            "OUTPUT/NAME, which appears "
            "whole or not at all. A rerun skips finished captures, and failed ones whose files did not change (--force "
            "redoes them); a failing capture is reported and the others "
            "go on (exit status 1); Ctrl-C leaves no partial output. OUTPUT/index.html is the gallery (warp-highlights "
            "serve OUTPUT), "
            "OUTPUT/collection.json the same for programs. Needs Dask distributed: pip install "
            "'warp-highlights[collection]'."),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
