"""Stages 3-4 of the tracker (render_core/tracking: correspond, fit, track) and ``blendsplat track``: the known-answer
test - the project's own synthetic head video (frames rendered with known tracking), encoded as H.264, tracked
back - comparing the fitted open head with the truth in pixels, head rotation and jaw opening."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from render_core.data.portable import read_dataset, validate_dataset
from render_core.facemodel.open_head import open_head
from render_core.tracking.correspond import FACE_OVAL, SHIPPED, build_correspondence, load_correspondence
from render_core.tracking.fit import matrix_to_axis_angle, rodrigues
from render_core.tracking.known_answer import known_answer
from render_core.tracking.known_answer import synth_video as known_answer_video


def synth_video(tmp_path, frames: int, size: int, seed: int):
    truth, video = known_answer_video(tmp_path, frames, size, seed)
    return truth.tracking, video


def run_track(video, out, size: int) -> dict:
    cmd = [sys.executable, "-m", "service.cli", "track", str(video), "--out", str(out), "--crop", "none",
           "--size", str(size), "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "track: fit" in done.stderr  # progress on stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1
    return json.loads(lines[0])


# ----------------------------------------------------------------------------------------------------- units
def test_rodrigues_and_its_inverse_agree():
    r = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [3.0, 0.1, 0.0]], dtype=torch.float64)
    R = rodrigues(r)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    assert torch.allclose(matrix_to_axis_angle(R), r, atol=1e-9)


def test_the_pose_jacobian_matches_finite_differences():
    from render_core.tracking.fit import R0, jacobian, projection

    gen = torch.Generator().manual_seed(4)
    X = torch.randn(3, 7, 3, generator=gen, dtype=torch.float64) * 0.05  # head points, metres
    p = torch.tensor([[0.1, -0.2, 0.05, 0.01, 0.02, 0.6], [0.0, 0.3, -0.1, -0.02, 0.0, 0.5],
                      [-0.2, 0.0, 0.2, 0.0, -0.01, 0.7]], dtype=torch.float64)
    c = torch.tensor([128.0, 120.0], dtype=torch.float64)

    def pixels(rotation_step: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        R = R0 @ rodrigues(p[:, :3]) @ rodrigues(rotation_step)  # the step on the right, as the fit takes it
        return projection(X @ R.transpose(1, 2) + t[:, None], 500.0, c)[0]

    R = R0 @ rodrigues(p[:, :3])
    _, dU = projection(X @ R.transpose(1, 2) + p[:, None, 3:], 500.0, c)
    J = jacobian(dU, R, X)  # [N, L, 2, 6]
    eps = 1e-6
    for k in range(6):
        step, t = torch.zeros(3, 3, dtype=torch.float64), p[:, 3:].clone()
        (step[:, k] if k < 3 else t[:, k - 3]).add_(eps)
        minus_step, minus_t = torch.zeros(3, 3, dtype=torch.float64), p[:, 3:].clone()
        (minus_step[:, k] if k < 3 else minus_t[:, k - 3]).sub_(eps)
        numeric = (pixels(step, t) - pixels(minus_step, minus_t)) / (2 * eps)
        assert torch.allclose(J[..., k], numeric, atol=1e-4, rtol=1e-6), k


def test_the_pixel_jacobian_matches_finite_differences_of_an_image():
    """photometric.pixel_jacobian: d(grey)/d(pose, expressions) of points sampled in an image (an analytic one here,
    g(u, v) = sin(u / 7) cos(v / 5)), against central differences of the grey levels themselves."""
    from render_core.tracking.fit import R0, projection
    from render_core.tracking.photometric import pixel_jacobian

    gen = torch.Generator().manual_seed(6)
    n, m, k = 2, 9, 4
    X0 = torch.randn(n, m, 3, generator=gen, dtype=torch.float64) * 0.05
    B = torch.randn(k, m, 3, generator=gen, dtype=torch.float64) * 0.01  # the points' expression basis
    e = torch.rand(n, k, generator=gen, dtype=torch.float64) * 0.5
    p = torch.tensor([[0.1, -0.2, 0.05, 0.01, 0.02, 0.6], [0.0, 0.3, -0.1, -0.02, 0.0, 0.5]], dtype=torch.float64)
    c = torch.tensor([128.0, 120.0], dtype=torch.float64)

    def image(u: torch.Tensor) -> torch.Tensor:
        return torch.sin(u[..., 0] / 7) * torch.cos(u[..., 1] / 5)

    def greys(rotation_step: torch.Tensor, t: torch.Tensor, expr: torch.Tensor) -> torch.Tensor:
        R = R0 @ rodrigues(p[:, :3]) @ rodrigues(rotation_step)
        X = X0 + torch.einsum("nk,kmc->nmc", expr, B)
        return image(projection(X @ R.transpose(1, 2) + t[:, None], 500.0, c)[0])

    R = R0 @ rodrigues(p[:, :3])
    X = X0 + torch.einsum("nk,kmc->nmc", e, B)
    u, dU = projection(X @ R.transpose(1, 2) + p[:, None, 3:], 500.0, c)
    gradient = torch.stack([torch.cos(u[..., 0] / 7) * torch.cos(u[..., 1] / 5) / 7,
                            -torch.sin(u[..., 0] / 7) * torch.sin(u[..., 1] / 5) / 5], -1)  # [N, M, 2]
    dG = (gradient[..., None] * dU).sum(2, keepdim=True)  # as refine_chunk forms it: [N, M, 1, 3]
    J = pixel_jacobian(dG, R, X, B)
    assert J.shape == (n, m, 6 + k) and pixel_jacobian(dG, R, X).shape == (n, m, 6)
    eps = 1e-6
    for col in range(6 + k):
        plus = [torch.zeros(n, 3, dtype=torch.float64), p[:, 3:].clone(), e.clone()]
        minus = [torch.zeros(n, 3, dtype=torch.float64), p[:, 3:].clone(), e.clone()]
        which, i = (0, col) if col < 3 else (1, col - 3) if col < 6 else (2, col - 6)
        plus[which][:, i] += eps
        minus[which][:, i] -= eps
        numeric = (greys(*plus) - greys(*minus)) / (2 * eps)
        assert torch.allclose(J[..., col], numeric, atol=1e-6, rtol=1e-5), col


def test_the_normal_equations_are_those_of_the_weighted_jacobian():
    """normal_equations (float32 inside, one buffer) against J^T W J and J^T W r built plainly in float64."""
    from render_core.tracking.fit import Problem, jacobian, normal_equations, projection

    problem = Problem(open_head())
    gen = torch.Generator().manual_seed(5)
    n, L = 4, problem.L
    rotation = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.2
    R = rodrigues(rotation)
    X = problem.anchors(rotation) + torch.einsum("nk,klc->nlc", torch.rand(n, 52, generator=gen,
                                                                            dtype=torch.float64) * 0.3, problem.B)
    _, dU = projection(X @ R.transpose(1, 2) + torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64), 900.0,
                       torch.tensor([256.0, 256.0], dtype=torch.float64))
    w = torch.rand(n, L, generator=gen, dtype=torch.float64)
    r = torch.randn(n, L, 2, generator=gen, dtype=torch.float64)
    expressions = (dU @ R[:, None]) @ problem.Bt  # [N, L, 2, 52]: d(pixels)/d(expression), per frame and point
    for Bt, J in ((None, jacobian(dU, R, X)), (problem.Bt, torch.cat([jacobian(dU, R, X), expressions], -1))):
        J = J.reshape(n, 2 * L, -1)
        W = w.repeat_interleave(2, 1)[..., None]
        H, g = normal_equations(dU, R, X, Bt, w, r)
        H_ref, g_ref = J.transpose(1, 2) @ (W * J), J.transpose(1, 2) @ (W * r.reshape(n, -1, 1))
        assert H.dtype == g.dtype == torch.float64 and H.shape == H_ref.shape and g.shape == g_ref.shape
        assert torch.allclose(H, H_ref, rtol=1e-4, atol=1e-3 * H_ref.abs().max().item() * 1e-3)
        assert torch.allclose(g, g_ref, rtol=1e-4, atol=1e-3 * g_ref.abs().max().item() * 1e-3)


def test_the_shipped_correspondence_is_what_the_builder_makes():
    shipped = load_correspondence(SHIPPED)
    built, report = build_correspondence()
    assert np.array_equal(shipped.landmarks, built.landmarks)
    # the same surface points; a point on an edge may be named through either triangle that shares the edge (weight
    # 0 on the third vertex), and which one the builder picks can flip between machines
    template = open_head().template.double()
    assert torch.allclose(shipped.points(template), built.points(template), atol=1e-6)
    assert not set(FACE_OVAL) & set(shipped.landmarks.tolist())
    assert list(shipped.landmarks[-2:]) == [468, 469] and len(shipped.landmarks) > 350
    assert report["residual_px_max"] < 8.0  # in the front view, after the multi-view refinement (measured 6.0 px)


def test_the_calibration_moves_landmarks_to_where_the_face_mesh_puts_them():
    """Offsets learnt from a short render with a known answer bring the landmarks' points closer to what the face
    mesh finds than the bare surface points (render_core/tracking/calibrate.py), and ship with the correspondence."""
    from render_core.tracking.calibrate import calibrate

    model = open_head()
    shipped = load_correspondence(SHIPPED)
    offsets, report = calibrate(model, shipped, seeds=(5,), frames=12, size=256)
    assert offsets.shape == (len(shipped.landmarks), 3, 4 + model.num_expressions)
    assert np.isfinite(offsets).all()
    assert report["median_px_after"] < 0.9 * report["median_px_before"], report
    assert shipped.offsets is not None and shipped.offsets.shape == offsets.shape


# ------------------------------------------------------------------------------------------ the known answer
@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("track")
    truth, video = synth_video(tmp, frames=16, size=256, seed=31)  # not a calibration seed (calibrate.SEEDS)
    report = run_track(video, tmp / "out", 256)
    return truth, tmp / "out", report


def test_track_writes_a_valid_dataset_with_a_report(tracked):
    truth, out, report = tracked
    assert validate_dataset(out) == []
    ds = read_dataset(out)
    tr = ds.tracking
    assert len(ds) == 16 == report["frames_kept"] and report["frames_dropped"]["count"] == 0
    assert list(tr.test) == list(truth.test) and list(tr.train) == list(truth.train)  # the last 15% held out
    assert tr.expression_names == truth.expression_names and tr.joint_names == truth.joint_names
    for name in ("expression", "joint_rotations", "eyelids", "K", "R", "t", "shape"):
        assert getattr(tr, name).shape == getattr(truth, name).shape and getattr(tr, name).dtype == np.float32
    assert set(report["timing_ms"]) == {"decode", "landmarks", "fit", "write"}
    assert (out / "contact_sheet.png").is_file()
    mask = ds.mask(0)
    truth_mask = read_dataset(out.parent / "truth").mask(0)
    inter = ((mask > 0.5) & (truth_mask > 0.5)).sum()
    # the head matte holds the rendered head and, cut to the fitted head's silhouette and then by colour, hardly
    # anything of the black background: measured 0.999 of it on the head (0.92 cut by the silhouette only, 0.78
    # before that)
    assert inter / (truth_mask > 0.5).sum() > 0.97 and inter / (mask > 0.5).sum() > 0.98


def test_the_fit_recovers_the_known_tracking(tracked):
    truth, out, report = tracked
    model = open_head()
    figures = known_answer(model, truth, read_dataset(out).tracking)
    print("known answer, 16 frames at 256 px:", {k: round(v, 2) for k, v in figures.items()}, report)
    # Figures at 256 px (goal: 1.5 px at 512, i.e. 0.75 px here; floor 2.5 px at 512): see the docs
    # measured (every skin vertex, as the check counts): 0.96 px median (about 1.9 px at 512), rotation 0.80 deg
    # median, jaw 0.87 deg (without the expression pass: 0.97 px, 0.76 deg, 1.0 deg; one pass of the photometric
    # refinement, cos > 0.3: 1.06 px, 0.95 deg); landmark fit
    # alone 1.16 px and 1.13 deg; before the calibrated correspondence 1.54 px and 2.8 deg
    assert figures["median_vertex_px"] < 1.4
    assert figures["median_head_rotation_deg"] < 1.4
    assert figures["median_jaw_deg"] < 3.0
    assert report["reprojection_px"] < 1.0


def test_the_photometric_refinement_lowers_the_pose_error(tracked, tmp_path):
    """The same clip tracked with the landmark fit alone: the refined poses (the fixture's, the default) are closer
    to the truth. Measured, 16 frames at 256 px: 1.16 -> 0.97 px, rotation 1.13 -> 0.76 deg; 60 frames at 512 px:
    seed 41 2.50 -> 2.04 px and 1.67 -> 0.81 deg, seed 57 1.85 -> 1.01 px and 1.13 -> 0.30 deg."""
    from render_core.tracking.track import track_video

    truth, out, _ = tracked
    report = track_video(out.parent / "clip.mp4", tmp_path / "landmarks-only", size=256, crop="none",
                         photometric="off")
    assert report["frames_kept"] == 16
    model = open_head()
    refined = known_answer(model, truth, read_dataset(out).tracking)
    plain = known_answer(model, truth, read_dataset(tmp_path / "landmarks-only").tracking)
    assert refined["median_head_rotation_deg"] < plain["median_head_rotation_deg"] - 0.05, (refined, plain)
    assert refined["median_vertex_px"] < plain["median_vertex_px"], (refined, plain)


def test_the_expression_pass_brings_the_expressions_closer(tracked, tmp_path):
    """The same clip with the poses alone refined on the pixels (``photometric="poses"``): the default's last pass,
    poses and expressions together, moves the head's vertices by expressions closer to the truth's. Measured, 16
    frames at 256 px: 0.90 -> 0.80 mm (the mean distance the expressions move the vertices from the truth's), median
    vertex error 0.973 -> 0.960 px, rotation 0.76 -> 0.80 deg, jaw 1.04 -> 0.87 deg."""
    from render_core.tracking.track import track_video

    truth, out, _ = tracked
    track_video(out.parent / "clip.mp4", tmp_path / "poses-only", size=256, crop="none", photometric="poses")
    model = open_head()
    both = known_answer(model, truth, read_dataset(out).tracking)
    poses = known_answer(model, truth, read_dataset(tmp_path / "poses-only").tracking)
    print("expression pass:", both, "poses only:", poses)
    assert both["mean_expression_mm"] < poses["mean_expression_mm"] - 0.05, (both, poses)
    assert both["median_vertex_px"] < poses["median_vertex_px"], (both, poses)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [41, 57])  # not calibration seeds
def test_the_fit_recovers_longer_clips_at_512(tmp_path, seed):
    truth, video = synth_video(tmp_path, frames=60, size=512, seed=seed)
    report = run_track(video, tmp_path / "out", 512)
    figures = known_answer(open_head(), truth, read_dataset(tmp_path / "out").tracking)
    print(f"known answer, seed {seed}, 60 frames at 512 px:", {k: round(v, 2) for k, v in figures.items()},
          report["timing_ms"], report["frames_per_second"])
    # Measured (seeds 41, 57; every skin vertex): 2.04 / 1.01 px median (the floor is 2.5 px, the goal 1.5 px),
    # rotation 0.81 / 0.30 deg median, jaw 1.8 / 0.9 deg median (the refinement's first version: 1.97 / 1.05 px,
    # 1.25 / 0.31 deg; landmark fit alone: 2.50 / 1.85 px, 1.67 / 1.13 deg). Regression bounds:
    assert figures["median_vertex_px"] < 2.5
    assert figures["median_head_rotation_deg"] < 1.4
    assert figures["median_jaw_deg"] < 3.0


def test_bench_track_reports_the_stage_split_and_the_known_answer():
    """``blendsplat bench track --json``: one JSON line with the stage split, frames per second and the known answer
    of each seed (a short clip here; the benchmark's default is 150 frames at 512 px)."""
    done = subprocess.run([sys.executable, "-m", "service.cli", "bench", "track", "--frames", "12", "--size", "128",
                           "--seeds", "31", "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    (run,) = report["runs"]
    assert set(run["timing_ms"]) == {"decode", "landmarks", "fit", "write"}
    assert run["frames_per_second"]["landmarks_and_fit"] > 0 and report["landmarks_and_fit_fps"] > 0
    assert run["known_answer"]["frames"] == 12
    assert 0 <= report["median_vertex_px"] < 10 and 0 <= report["median_head_rotation_deg"] < 15


def test_an_unknown_refinement_is_refused_by_name_before_anything_is_written(tmp_path):
    """track_video's ``photometric`` is one of on, poses, off; another value is a TrackingError naming the field,
    raised before the video is read, and the output folder is not made."""
    from render_core.errors import TrackingError
    from render_core.tracking.track import track_video

    with pytest.raises(TrackingError, match="unknown refinement 'yes'; one of on, poses, off") as raised:
        track_video(tmp_path / "missing.mp4", tmp_path / "out", photometric="yes")
    assert raised.value.field == "photometric"
    assert not (tmp_path / "out").exists()


def test_a_known_focal_length_is_used_instead_of_searched(tmp_path):
    """``--focal``: the focal length the user knows (a phone records it) is the tracking's, not an estimate; a
    nonsensical one is refused naming ``focal``."""
    _, video = synth_video(tmp_path, frames=12, size=128, seed=31)
    cmd = [sys.executable, "-m", "service.cli", "track", str(video), "--crop", "none", "--size", "128", "--json"]
    done = subprocess.run(cmd + ["--out", str(tmp_path / "out"), "--focal", "250"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["focal_px"] == 250.0
    assert read_dataset(tmp_path / "out").tracking.K[0, 0, 0] == 250.0
    done = subprocess.run(cmd + ["--out", str(tmp_path / "bad"), "--focal", "-3"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode != 0 and "focal" in done.stderr and not (tmp_path / "bad" / "tracking.npz").exists()


def test_a_video_with_too_few_frames_is_refused_as_too_short_and_nothing_is_written(tmp_path):
    _, video = synth_video(tmp_path, frames=6, size=64, seed=31)
    done = subprocess.run([sys.executable, "-m", "service.cli", "track", str(video), "--out", str(tmp_path / "out"),
                           "--crop", "none", "--size", "64"], capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "too short" in done.stderr and "frames" in done.stderr, done.stderr[-500:]
    assert not (tmp_path / "out" / "tracking.npz").exists()


def test_masks_made_on_worker_threads_come_back_in_order_and_bounded():
    import threading

    from render_core.tracking.track import _with_masks

    pulled, made = [], []

    def frames():
        for k in range(20):
            pulled.append(k)
            yield k, np.full((4, 4, 3), k, np.uint8)

    def mask_of(k, rgb):
        made.append(threading.current_thread().name)
        return rgb[..., 0] * 2

    serial = list(_with_masks(frames(), mask_of, 1))
    assert set(made) == {threading.current_thread().name}
    made.clear()
    pulled.clear()
    out = []
    for k, rgb, mask in _with_masks(frames(), mask_of, 2, ahead=3):
        assert len(pulled) <= k + 1 + 3  # never more than `ahead` frames decoded ahead of the one written
        out.append((k, rgb, mask))
    assert [k for k, _, _ in out] == list(range(20)) == [k for k, _, _ in serial]
    assert all(np.array_equal(a[2], b[2]) and np.array_equal(a[1], b[1]) for a, b in zip(out, serial, strict=True))
    assert len(made) == 20 and all(name.startswith("matte") for name in made)

    def broken(k, rgb):
        if k == 5:
            raise ValueError("frame 5")
        return rgb[..., 0]

    with pytest.raises(ValueError, match="frame 5"):
        list(_with_masks(frames(), broken, 2))


def test_the_second_pass_takes_each_points_colour_from_the_whole_video(monkeypatch):
    """refine_on_pixels: on the first pass a chunk's colours add the chunks before it; on the second, every other
    chunk's sums from the first pass (the chunk's own come fresh from its refined poses). The expression pass that
    follows refines the expressions too, on more points (the moving ones added), whose colours start afresh."""
    from render_core.tracking import photometric
    from render_core.tracking.fit import R0, FitResult

    n, seen, kinds = 6, [], []

    def fake_chunk(problem, model, p, obs, images, f, c, points, others=None, expressions=False, focal=False):
        seen.append(None if others is None else others.clone())
        kinds.append((expressions, len(points)))
        mark = float(images[0, 0, 0])  # which chunk: its frames carry its number
        return p, torch.full((len(photometric.SCHEDULE), 2, 3), mark, dtype=torch.float64), None

    monkeypatch.setattr(photometric, "refine_chunk", fake_chunk)
    fit = FitResult(np.diag([500.0, 500.0, 1.0]), np.broadcast_to(R0.numpy(), (n, 3, 3)).copy(),
                    np.tile([0.0, 0.0, 0.6], (n, 1)), np.zeros((n, 52)), np.zeros(n), [])
    chunks = [([0, 1], np.full((2, 4, 4), 1.0, np.float32)), ([2, 3], np.full((2, 4, 4), 2.0, np.float32)),
              ([4, 5], np.full((2, 4, 4), 4.0, np.float32))]
    photometric.refine_on_pixels(open_head(), fit, np.zeros((n, 468, 3)), np.zeros((n, 2, 5, 3)),
                                 lambda: iter(chunks), passes=2, expression_passes=1)
    values = [None if o is None else float(o.flatten()[0]) for o in seen]
    # pass 1 (sums 1, 2, 4): nothing before the first chunk, then the running sums; pass 2: the other chunks' sums;
    # the expression pass: running sums again, of its own points
    assert values == [None, 1.0, 3.0, 6.0, 5.0, 3.0, None, 1.0, 3.0]
    still, both = photometric.POINTS, photometric.EXPRESSION_RIGID + photometric.EXPRESSION_POINTS
    assert kinds == [(False, still)] * 6 + [(True, both)] * 3


def test_the_shared_parameters_terms_are_the_joint_systems():
    """photometric.marginal: the Gauss-Newton step of one parameter that every frame shares (log f), with each
    frame's own parameters free, equals that parameter's part of the step of the whole joint system solved at once
    (the Schur complement; a dropped coupling term or a sign error makes it differ)."""
    from render_core.tracking.photometric import marginal

    gen = torch.Generator().manual_seed(3)
    n, a = 5, 6
    J = torch.randn(n, 20, a + 1, generator=gen, dtype=torch.float64)  # per frame: its own columns, then the shared
    r = torch.randn(n, 20, generator=gen, dtype=torch.float64)
    H, Hf, hff = J[..., :a].transpose(1, 2) @ J[..., :a], (J[..., :a] * J[..., a:]).sum(1), (J[..., a] ** 2).sum(1)
    g, gf = (J[..., :a] * r[..., None]).sum(1), (J[..., a] * r).sum(1)
    full = torch.zeros(n * a + 1, n * a + 1, dtype=torch.float64)
    rhs = torch.zeros(n * a + 1, dtype=torch.float64)
    for i in range(n):
        full[i * a:(i + 1) * a, i * a:(i + 1) * a] = H[i]
        full[i * a:(i + 1) * a, -1] = full[-1, i * a:(i + 1) * a] = Hf[i]
        rhs[i * a:(i + 1) * a] = g[i]
    full[-1, -1], rhs[-1] = hff.sum(), gf.sum()
    joint = torch.linalg.solve(full, -rhs)[-1]
    curvature, gradient = marginal(H, g, Hf, hff, gf)
    assert torch.isclose(-gradient / curvature, joint, rtol=1e-9)
    assert curvature > 0


def _exact_landmarks(model, n: int, f: float, size: int, expressions: dict[str, float]):
    """Landmarks and irises that the fit's own point model puts exactly where a head ``n`` frames turning, with
    ``expressions`` held, projects through focal length ``f`` (no detector's bias): (landmarks, iris)."""
    from render_core.tracking.fit import R0, P, Problem

    problem = Problem(model)
    p = torch.zeros(n, P, dtype=torch.float64)
    p[:, 1] = torch.linspace(-0.35, 0.35, n)  # yaw
    p[:, 0] = torch.linspace(0.15, -0.1, n)  # pitch
    for name, value in expressions.items():
        p[:, 6 + model.expression_names.index(name)] = value
    p[:, 3:6] = -(R0 @ problem.T.mean(0))  # the template's centre on the optical axis, 0.55 m away
    p[:, 5] += 0.55
    c = torch.tensor([size / 2, size / 2], dtype=torch.float64)
    both = np.zeros((n, 470, 2))
    both[:, problem.corr.landmarks] = problem.project(p, f, c).numpy()
    landmarks = np.concatenate([both[:, :468], np.zeros((n, 468, 1))], -1)
    iris = np.zeros((n, 2, 5, 3))
    iris[:, :, 0, :2] = both[:, 468:]
    return landmarks, iris


def test_the_focal_length_is_searched_again_with_the_fitted_expressions_held():
    """fit_frames: a face held in a strong expression fits a neutral head's rigid pose badly, and the focal
    length that makes that misfit least is biased (the open head's landmarks at 256 px: about 13% low on the
    known-answer videos); the second search, with each keyframe's fitted expressions held, comes closer. Exact
    landmarks here (a smile, brows up, the jaw half open): the first search's best is off by more than the
    second's."""
    from render_core.tracking.fit import fit_frames

    model = open_head()
    truth = 500.0
    landmarks, iris = _exact_landmarks(model, 12, truth, 256, {"jawOpen": 0.5, "mouthSmileLeft": 0.6,
                                                               "mouthSmileRight": 0.6, "browInnerUp": 0.7})
    fit = fit_frames(model, landmarks, iris, 256, 256, smooth=0.0)
    first = min(fit.focal_search[:10], key=lambda pair: pair[1])[0]  # the rigid search's best (its 10 tries)
    found = float(fit.K[0, 0])
    print("focal: truth", truth, "rigid search", first, "searched again", found)
    # measured: the rigid search 455.5 px, searched again 485.7 (the expression prior still shrinks the fitted
    # expressions a little)
    assert abs(found / truth - 1) < 0.04
    assert abs(found / truth - 1) < abs(first / truth - 1) - 0.04


@pytest.mark.slow
def test_the_pixels_refine_the_focal_length(tmp_path):
    """refine_on_pixels: a focal length 15% short (as the landmark search's alone was on these videos) moves toward
    the truth with each pose pass (a Gauss-Newton step on log f, every frame's pose free), each frame's head moved
    as far as the step asks; ``focal=False`` (what ``track --focal`` uses) keeps it. 60 frames at 256 px (on the
    16-frame fixture the pixels say too little of it: it stays put)."""
    import av

    from render_core.tracking import photometric
    from render_core.tracking.fit import fit_frames
    from render_core.tracking.landmarks import track_landmarks

    truth, video = synth_video(tmp_path, frames=60, size=256, seed=31)
    with av.open(str(video)) as clip:
        frames = [frame.to_ndarray(format="rgb24") for frame in clip.decode(video=0)]
    found = track_landmarks(iter(frames))
    landmarks, iris = found.landmarks[found.kept], found.iris[found.kept]
    true_focal = float(truth.K[0, 0, 0])
    model = open_head()
    fit = fit_frames(model, landmarks, iris, 256, 256, focal=0.85 * true_focal)
    grey = np.stack([photometric.grey(f) for f in frames])

    def chunks():
        yield list(range(len(frames))), grey

    kept = photometric.refine_on_pixels(model, fit, landmarks, iris, chunks, focal=False)
    refined = photometric.refine_on_pixels(model, fit, landmarks, iris, chunks)
    print("focal: truth", true_focal, "start", 0.85 * true_focal, "refined", refined.K[0, 0])
    assert kept.K[0, 0] == fit.K[0, 0]
    assert abs(refined.K[0, 0] / true_focal - 1) < 0.15 - 0.02
    plain, better = (known_answer(model, truth, _as_tracking(model, truth, r)) for r in (kept, refined))
    assert better["median_vertex_px"] < plain["median_vertex_px"], (plain, better)


def _as_tracking(model, truth, fit):
    """A fit (:class:`~render_core.tracking.fit.FitResult`) as the tracking ``track`` writes of it."""
    from dataclasses import replace

    n = len(fit.expression)
    return replace(truth, expression_names=list(model.expression_names), expression=fit.expression.astype(np.float32),
                   K=np.broadcast_to(fit.K, (n, 3, 3)).astype(np.float32), R=fit.R.astype(np.float32),
                   t=fit.t.astype(np.float32), joint_rotations=np.zeros_like(truth.joint_rotations),
                   eyelids=np.zeros_like(truth.eyelids))


def test_the_focal_length_takes_one_step_a_pose_pass_from_every_chunks_terms(monkeypatch):
    """refine_on_pixels: after each pose pass the chunks' marginal terms of log f are summed and one step taken
    (the expression pass takes none, and a step is at most FOCAL_STEP); each frame's translation is scaled with it,
    so the output's K and t carry both passes' steps."""
    from render_core.tracking import photometric
    from render_core.tracking.fit import R0, FitResult

    n, focals = 4, []

    def fake_chunk(problem, model, p, obs, images, f, c, points, others=None, expressions=False, focal=False):
        focals.append((round(f, 6), focal))
        terms = None if not focal else torch.tensor([2.0, -0.05], dtype=torch.float64)  # a step of +0.025 each
        return p, torch.ones(len(photometric.SCHEDULE), 2, 3, dtype=torch.float64), terms

    monkeypatch.setattr(photometric, "refine_chunk", fake_chunk)
    fit = FitResult(np.diag([500.0, 500.0, 1.0]), np.broadcast_to(R0.numpy(), (n, 3, 3)).copy(),
                    np.tile([0.01, 0.0, 0.6], (n, 1)), np.zeros((n, 52)), np.zeros(n), [])
    chunks = [([0, 1], np.zeros((2, 4, 4), np.float32)), ([2, 3], np.zeros((2, 4, 4), np.float32))]
    out = photometric.refine_on_pixels(open_head(), fit, np.zeros((n, 468, 3)), np.zeros((n, 2, 5, 3)),
                                       lambda: iter(chunks), passes=2, expression_passes=1)
    step = np.exp(2 * 0.05 / (2 * 2.0))  # both chunks' terms summed: -(-0.1) / 4
    once, twice = round(500.0 * step, 6), round(500.0 * step ** 2, 6)
    assert focals == [(500.0, True)] * 2 + [(once, True)] * 2 + [(twice, False)] * 2
    assert out.K[0, 0] == pytest.approx(500 * step ** 2) and out.K[1, 1] == out.K[0, 0]
    np.testing.assert_allclose(out.t, fit.t * step ** 2)
    off = photometric.refine_on_pixels(open_head(), fit, np.zeros((n, 468, 3)), np.zeros((n, 2, 5, 3)),
                                       lambda: iter(chunks), passes=2, expression_passes=1, focal=False)
    assert off.K[0, 0] == 500.0 and np.array_equal(off.t, fit.t)
