"""The ``fit`` command of ``warp-highlights``: a dataset folder -> a highlight-field file."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..model.config import RESIDUAL_KINDS
from ..model.errors import InputError
from .args import (
    Command,
    add_pixel_limit_option,
    check_device,
    check_output_file,
    exposure_option,
    in_range,
    pixel_limit,
    size_option,
)

__all__ = ["COMMANDS"]


def _fit_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, nargs="?", help="dataset folder (a .lp light file and its images)")
    output = parser.add_argument("-o", "--output", type=Path, required=True,
                                 help="highlight-field file to write (e.g. donut.whf)")
    parser.add_argument(
        "--size", type=size_option("working size"),
        help="working resolution WIDTHxHEIGHT, same aspect ratio, at most the images' size (default: the images' size)")
    parser.add_argument(
            "--set",
            dest="overrides",
            action="append",
            default=[],
            metavar="STAGE.NAME=VALUE",
            help="override a hyper-parameter, e.g. --set retarget.c_str=0.01 --set estimation.iterations=600 "
            "(repeatable; --list-settings shows them all)",
        )
    parser.add_argument("--holdout-every", type=in_range(int, 2, 1000), metavar="K",
                        help="fit without lights 0, K, 2K, ... of the dataset, to score them later "
                             "(evaluate FIELD DATASET)")
    parser.add_argument("--list-settings", action=_ListSettings, output=output,
                        help="print every hyper-parameter with its default and exit (no DATASET or -o needed)")
    parser.add_argument("--residual", choices=list(RESIDUAL_KINDS), default=None,
                        help="what relighting adds the moved highlights to (the images minus their own "
                             "highlights), the setting residual.kind: lowrank (low-rank 8- or 16-bit bases, about a "
                             "quarter of the 8-bit capture; seconds), learned (9 numbers per pixel and an MLP, "
                             "trained for up to residual.learned_epochs or learned_seconds: about 10 s on a GPU, 2 "
                             "minutes on a CPU; where the Gaussians move, a check decides whether it keeps them or "
                             "learns the images alone), images (uncompressed float16, exact at the captured "
                             "lights), none (then use --diffuse), or auto (default: learned on CUDA, and on the CPU "
                             "where the capture learns in time (residual.cpu_learned_epochs), else lowrank; lowrank "
                             "for one-channel captures)")
    parser.add_argument("--diffuse", choices=["lambert", "images", "none"], default="none",
                        help="also store the per-pixel Lambertian model (lambert), that plus the diffuse images "
                             "(images), or not (default none)")
    parser.add_argument(
            "--exposure",
            type=exposure_option,
            default=None,
            help="multiply the radiance by this before fitting, or 'auto' (99.9th percentile -> 1); the "
                 "thresholds assume "
            "display white is 1 (default: auto for JPEG/PNG/TIFF photographs, 1 for EXR/HDR radiance); "
            "relighting undoes it",
        )
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--workers", type=in_range(int, 1, 4096),
                        help="CPU threads for the fitting stages, 1..4096 (default: one per core)")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    parser.add_argument("--report", type=Path, help="also write the fit report as JSON to this file")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing output files (the field and the report)")
    add_pixel_limit_option(parser)


class _ListSettings(argparse.Action):
    """``--list-settings``: a flag that makes ``-o`` optional for this run (nothing is written)."""

    def __init__(self, option_strings, dest, *, output: argparse.Action, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=False, **kwargs)
        self.output = output

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, True)
        self.output.required = False  # argparse checks the required options after every argument is read


EARLY_LOAD_BYTES = 1 << 29
"""``fit`` decodes a capture of at most this many float32 bytes (512 MiB: 250 lights at 480x270 are 389 MB) while Warp
starts, and a larger one only once Warp has found the device: a wrong ``--device`` then costs at most a short
read before its error line, while at 480x270 the reading hides the wait for Warp's start."""


def residual_overrides(kind: str | None) -> list[str]:
    """The ``--set`` overrides ``--residual KIND`` stands for (put before any ``--set``, which can still change it)."""
    return [] if kind is None else [f"residual.kind={kind}"]


def _thread_lock_for_progress_bars() -> None:
    """Guard this process's tqdm bars with a thread lock alone. tqdm's default lock also makes a
    multiprocessing one, importing ``multiprocessing`` (time of the loading thread, under the GIL the
    pipeline's imports need); this command's bars are all drawn by its own threads."""
    import threading

    from tqdm import tqdm

    if "_lock" not in vars(tqdm):  # not where a bar (or the program embedding us) has set it already
        tqdm.set_lock(threading.RLock())


def _check_fit(args) -> None:
    if not args.list_settings and args.dataset is None:
        raise InputError("fit needs a DATASET folder and -o FIELD, e.g. warp-highlights fit data/donut -o donut.whf")


def _run_fit(args) -> int:
    from ..model.config import FitSettings

    overrides = list(args.overrides)
    overrides[:0] = residual_overrides(args.residual)
    settings = FitSettings().with_overrides(overrides)
    if args.list_settings:
        _print_settings(settings.to_dict())
        return 0
    output = Path(args.output)
    check_output_file(output, overwrite=args.overwrite, inputs=[args.dataset])
    if args.report is not None:
        if Path(args.report).resolve() == output.resolve():
            raise InputError(f"--report {args.report} is the field file itself; give the report its own name")
        check_output_file(Path(args.report), overwrite=args.overwrite, inputs=[args.dataset])
    size = args.size
    from ..io.dataset import LoadStopped, ReflectanceField, capture_fingerprint
    from ..kernels.warmup import DeviceWarmup, InBackground
    from ..model.memory import PeakMemory

    started = time.perf_counter()  # the summary's time includes the pipeline's imports from here on

    def load(stop) -> tuple | None:  # in a thread, while the pipeline is imported: the decoding lets go of the GIL
        # a large capture decodes only once Warp has found the device (a wrong
        def device_found(stack_bytes: int) -> None:
            # --device is reported before it is read); a small one at once (reading it first costs less than waiting),
            # unless -v asks for Warp's own messages (the decoders' quieting of native stderr would hide those of its
            # start)
            if stack_bytes > EARLY_LOAD_BYTES or getattr(args, "verbose", False):
                warmup.started()
                if warmup.device is None:
                    raise LoadStopped("no device: check_device reports what is wrong")

        try:
            return load_images(stop, device_found)
        except LoadStopped:
            # check_device reports what is wrong (or, where Warp's start failed there only, the images load after it)
            return None

    # only what the fit uses (no held-out lights, no ground-truth components), shrunk to the working size as each image
    # is decoded; nothing here touches Warp (the host's peak alone)
    def load_images(stop, before_decoding=None) -> tuple:
        load_started = time.perf_counter()
        _thread_lock_for_progress_bars()
        with PeakMemory("cpu") as peak:
            loaded = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet,
                                           max_pixels=pixel_limit(args), size=size,
                                           heldout=False, components=False, stop=stop, before_decoding=before_decoding)
        return loaded, peak, time.perf_counter() - load_started

    warmup = None
    try:
        # Warp started while the pipeline is imported, the device's context while the images load
        warmup = DeviceWarmup(args.device)
        with InBackground(load, name="load") as background:
            try:
                from ..fit.pipeline import fit_field
                from ..io.fieldfile import save_field
            finally:
                warmup.started()  # Warp is started once, in one thread at a time
            device = check_device(args.device)
            from ..residual.kind import resolve_kind

            # waiting for the images anyway: the rate search's one late import now
            if resolve_kind(settings.residual.kind, device) == "lowrank" and not background.done():
                import scipy.optimize  # noqa: F401 (imported while the images load, not after)
            dataset, loading, load_seconds = background.result() or load_images(background.stop)
        capture = capture_fingerprint(dataset)  # the whole capture, before any hold-out split
        if args.holdout_every:
            dataset = dataset.split_every(args.holdout_every)
    finally:
        if warmup is not None:
            warmup.join()
    field = fit_field(  # its stage lines reach stderr through the warp_highlights logger (-q hides them)
        dataset, settings=settings, device=device, size=size, diffuse=args.diffuse, exposure=args.exposure,
        workers=args.workers, progress=not args.quiet
    )
    del dataset
    field.report["seconds"] = {"loading": round(load_seconds, 3), **field.report["seconds"]}
    if args.holdout_every:
        field.report["holdout_every"] = int(args.holdout_every)
    field.report["capture"] = capture
    saving_started = time.perf_counter()
    with PeakMemory(device) as saving:
        written = save_field(field, output)
    field.report["seconds"]["saving"] = round(time.perf_counter() - saving_started, 3)
    field.report["memory"] = {"loading": loading.report(), **field.report["memory"], "saving": saving.report()}
    field.report["file_bytes"] = written
    if args.report is not None:
        from ..io.atomic import atomic_file

        with atomic_file(Path(args.report), overwrite=args.overwrite) as temporary:
            temporary.write_text(json.dumps(field.report, indent=2))
    _print_fit_summary(field, output, written, time.perf_counter() - started)
    return 0


def _gaussian_size_text(report: dict) -> str:
    size = report.get("gaussian_size")
    return "" if size is None or list(size) == list(report["size"]) else f" (Gaussians fitted at {size[0]}x{size[1]})"


def _peak_text(memory: dict) -> str:
    """'host 1.2 GB (residual compression), device 3.4 GB (estimation)': each kind's largest stage."""
    from ..model.memory import bytes_text

    parts = []
    for kind in ("host", "device"):
        peaks = {stage: values[f"{kind}_peak_bytes"] for stage, values in memory.items()
                 if values.get(f"{kind}_peak_bytes") is not None}
        if peaks:
            stage = max(peaks, key=peaks.get)
            parts.append(f"{kind} {bytes_text(peaks[stage])} ({stage})")
    return ", ".join(parts) or "not known on this system"


def _print_settings(values: dict, prefix: str = "") -> None:
    for key, value in values.items():
        if isinstance(value, dict):
            _print_settings(value, prefix + key + ".")
        else:
            print(f"{prefix}{key}={value}")


def _print_fit_summary(field, output: Path, written: int, seconds: float) -> None:
    from ..io.fieldfile import field_size_report

    report = field.report
    est, ret = report["estimation"], report["retargeting"]
    count, quality = est["gaussians_per_light"], est["psnr_db"]
    print(f"wrote {output} ({written / 1e6:.2f} MB) in {seconds:.1f} s on {report['device']}")
    print(
        f"  lights {report['lights']} ({'dome' if report['dome'] else 'full sphere'}), directed edges "
        f"{report['directed_edges']}, "
        f"working size {report['size'][0]}x{report['size'][1]}{_gaussian_size_text(report)}, exposure "
        f"x{report['exposure']:.3g}"
    )
    print("  stage times: " + ", ".join(f"{name} {value:.1f} s" for name, value in report["seconds"].items()))
    print("  peak memory: " + _peak_text(report["memory"]))
    kept = (report.get("residual") or {}).get("kept_gaussians")
    print(f"  Gaussians per light: mean {count['mean']:.1f}, min {count['min']:.0f}, max {count['max']:.0f}"
          + (" (estimated; the field keeps none, see the checks below)" if kept == 0 else ""))
    print(f"  estimation PSNR (dB): mean {quality['mean']:.1f}, 5th percentile {quality['p5']:.1f}, min "
          f"{quality['min']:.1f}")
    print(f"  retargeting fit loss: source {ret['source_loss']['mean']:.1f} -> rigid {ret['rigid_loss']['mean']:.1f} "
          f"-> final {ret['loss']['mean']:.1f} (mean); improved on {100 * ret['improved_share']:.0f}% of edges")
    if ret.get("vanished_slots") is not None:
        print(f"  retargeted Gaussians that lost their highlight: {ret['vanished_slots']} vanished; sent where their "
              f"motion expects it: {ret.get('left_frame_slots', 0)} out of the frame, {ret.get('followed_slots', 0)} "
              f"inside it")
    print(f"  segmentation: {report['segmentation']['few_light_pixels']} pixels left all diffuse (fewer "
          f"than 4 lit samples)")
    residual = report.get("residual")
    if residual:
        resolved = report["residual_kind"]["resolved"]
        if resolved == "lowrank":
            budget, captured = residual.get("size_budget"), residual.get("captured_psnr_db")
            kind = (f"low rank (luminance {residual['luminance_rank']}"
                    + (f", chroma {residual['chroma_rank']}" if residual["chroma_rank"] else "")
                    + f", {residual['basis_bits']}-bit"
                    + (f"; {100 * budget:.0f}% of the capture, the captured lights back at {captured:.1f} dB"
                       if budget is not None and captured is not None else "") + ")")
        elif resolved == "learned":
            kind = f"learned ({residual['learned']['epochs']} epochs)"
        else:
            kind = "uncompressed images"
        share = residual.get("moving_specular_share")
        carried = "" if share is None else f" (carrying {100 * share:.0f}% of the specular energy)"
        glints, near = residual.get("incoherent_gaussians") or 0, residual.get("near_gaussians") or 0
        reasons = ([f"{glints} glints whose motion does not follow the light"] if glints else []) + (
            [f"{near} whose highlight travels too little between the lights to be moved"] if near else [])
        why = f" ({'; '.join(reasons)})" if reasons else ""
        left = residual.get("left_gaussians") or 0
        staying = (f"{left} are left to the learned residual" if left
                   else f"{residual['staying_gaussians']} blend in place")
        print(f"  residual: {kind}; {residual['moving_gaussians']} Gaussians move{carried}, {staying}{why}; "
              f"highlight colour {'per pixel' if residual['highlight_colour'] else 'white'}")
        coherence = residual.get("motion_coherence")
        if coherence is not None:
            print(f"  motion: the Gaussians follow the light with a median coherence of {coherence:.2f} "
                  "(1: highlights that glide, 0: glints that hop at random)")
        check = residual.get("move_check") or {}
        if check.get("lights"):
            verdict = ("the Gaussians move" if check["moves"]
                       else "the highlights stay in the residual (the field keeps no Gaussians)")
            print(f"  move check at {check['lights']} left-out lights: moving {check['moving_psnr_db']:.2f} dB, "
                  f"blending {check['blend_psnr_db']:.2f} dB (8-bit sRGB): {verdict}")
        learned = residual.get("learned_check") or {}
        if learned.get("lights"):
            sees = learned.get("sees_gaussians", False)
            verdict = (("the decoder keeps them as its inputs" if sees else "the learned residual keeps them")
                       if learned["keeps_gaussians"] else "the images are learned alone (the field keeps no Gaussians)")
            candidate = "a decoder that sees the moved Gaussians" if sees else "residual + moved Gaussians"
            exact = learned.get("exact_residual_psnr_db")
            exact = "" if exact is None else f" ({exact:.2f} dB with its residual exact)"
            margin = learned.get("tie_margin_db")
            rule = ""
            if margin is not None:
                rule = (f"kept unless the images alone lead by more than {margin:.1f} dB" if margin >= 0
                        else f"kept where the Gaussians lead by at least {-margin:.1f} dB")
                rule = f" ({'they glide: ' if learned.get('glides') else ''}{rule})"
            print(f"  learned check at {learned['lights']} left-out lights: {candidate} "
                  f"{learned['with_gaussians_psnr_db']:.2f} dB{exact}, "
                  f"images alone {learned['images_alone_psnr_db']:.2f} dB: {verdict}{rule}")
        weighing = residual.get("residual_interpolation") or {}
        if weighing.get("lights") and "rbf_psnr_db" in weighing:
            verdict = ("radial basis weights over every light" if weighing["chosen"] == "rbf"
                       else "the triangle's weights")
            print(f"  residual interpolation at {weighing['lights']} left-out lights: the triangle's "
                  f"{weighing['triangle_psnr_db']:.2f} dB, radial basis {weighing['rbf_psnr_db']:.2f} dB: {verdict}")
    parts = field_size_report(field)
    print("  file: " + ", ".join(f"{name} {value / 1e6:.2f} MB" for name, value in parts.items()))


COMMANDS = (
    Command("fit", _fit_arguments, _run_fit,
            help="fit a highlight field to a dataset (segmentation, estimation, retargeting)",
            description="Segment every image into diffuse and specular parts, fit a few Gaussians to each "
                        "specular image, "
            "re-fit every set onto its neighbours in the light triangulation, decide the Gaussians' paths "
            "and which of them "
            "move, keep each image's residual (the image minus its own moving highlights, compressed), and "
            "write everything to one highlight-field file.", check=_check_fit),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
