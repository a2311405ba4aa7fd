"""Stage 2 of the tracker (render_core/tracking: detect, mesh, segment, landmarks, runner): the shipped models, the
detector's decoding, a real photograph (scikit-image's astronaut), frames of the project's own synthetic head with
known tracking (landmarks against the projected open-head vertices), and tracking with gaps and several faces."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from render_core.errors import TrackingError
from render_core.tracking import fetch_models, runner
from render_core.tracking.detect import DETECTORS, anchors, detect_faces, weighted_nms
from render_core.tracking.landmarks import FaceTracker, find_face, track_landmarks
from render_core.tracking.mesh import POINTS
from render_core.tracking.segment import head_matte, mesh_silhouette, person_probability, sharpen_edge

# MediaPipe's points compared with the synthetic head: well defined on both (not silhouette points like the chin)
COMPARED = ("right_eye_outer", "right_eye_inner", "left_eye_inner", "left_eye_outer", "nose_tip", "mouth_right",
            "mouth_left")


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    data = pytest.importorskip("skimage.data")
    return data.astronaut()


# --------------------------------------------------------------------------------------------------- the crops
@pytest.mark.parametrize("k", [1, 2, 3])
def test_a_crop_samples_the_image_where_its_rect_maps_each_pixel(k):
    """A linear ramp stays linear through block means and bilinear sampling, so every crop pixel must read the ramp
    at Rect.to_image of its centre: rotated, mirrored and shrinking crops alike."""
    from render_core.tracking.geometry import Rect, crop

    H, W = 300, 400
    y, x = np.mgrid[0:H, 0:W] + 0.5  # pixel centres
    ramp = np.stack([0.5 * x + 0.25 * y, 200 - 0.3 * x + 0.1 * y], -1).astype(np.float32)
    rng = np.random.default_rng(k)
    for _ in range(6):
        out = int(rng.integers(24, 64))
        side = out * (k + rng.uniform(0.0, 0.9))
        rect = Rect(rng.uniform(150, 250), rng.uniform(120, 180), side, side * rng.uniform(0.9, 1.0),
                    rng.uniform(-0.6, 0.6), bool(rng.integers(2)))
        got = crop(ramp, rect, out, out)
        v, u = np.mgrid[0:out, 0:out] + 0.5
        at = rect.to_image(np.stack([u, v], -1), out, out)
        want = np.stack([0.5 * at[..., 0] + 0.25 * at[..., 1], 200 - 0.3 * at[..., 0] + 0.1 * at[..., 1]], -1)
        assert np.abs(got - want).max() < 0.05, (rect, np.abs(got - want).max())
    outside = crop(ramp, Rect(-500.0, -500.0, 50.0, 50.0), 16, 16)
    assert outside.shape == (16, 16, 2) and not outside.any()


def test_a_box_shrink_is_the_mean_of_whole_blocks():
    import torch
    import torch.nn.functional as F

    from render_core.tracking.geometry import box_shrink

    images = torch.rand(2, 3, 37, 50, generator=torch.Generator().manual_seed(0))
    for k in (1, 2, 3, 5):
        assert torch.allclose(box_shrink(images, k), F.avg_pool2d(images, k), atol=1e-6)


# -------------------------------------------------------------------------------------------------- the models
def test_the_shipped_models_match_their_manifest():
    assert fetch_models.check() == []
    manifest = runner._manifest()
    assert set(manifest) == set(fetch_models.FILES)
    assert {f"{n}.tflite" for n in runner.NAMES} <= set(manifest)


def test_an_altered_model_is_refused(tmp_path, monkeypatch):
    for f in runner.MODELS_DIR.iterdir():
        shutil.copy(f, tmp_path / f.name)
    with open(tmp_path / "iris_landmark.tflite", "r+b") as f:
        f.seek(1000)
        f.write(b"\x00\x01\x02")
    monkeypatch.setattr(runner, "MODELS_DIR", tmp_path)
    runner.model_path.cache_clear()
    try:
        with pytest.raises(TrackingError) as e:
            runner.model_path("iris_landmark")
        assert e.value.field == "model" and "sha256" in str(e.value)
        (tmp_path / "face_landmark.tflite").unlink()
        with pytest.raises(TrackingError) as e:
            runner.model_path("face_landmark")
        assert e.value.field == "model" and "missing" in str(e.value)
    finally:
        runner.model_path.cache_clear()


def test_the_detectors_anchor_grids_match_their_outputs():
    for name, size, layers, _ in DETECTORS.values():
        a = anchors(size, layers)
        model = runner.load_model(name)
        assert (len(a),) == (max(s[1] for s in model.output_shapes),)
    assert len(anchors(128, [(8, 2), (16, 6)])) == 896 and len(anchors(192, [(4, 1)])) == 2304


def test_weighted_nms_merges_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], float)
    kps = np.zeros((3, 6, 2))
    kps[1] += 1.0
    out = weighted_nms(boxes, kps, np.array([0.9, 0.3, 0.8]))
    assert len(out) == 2 and out[0][2] == 0.9 and out[1][2] == 0.8
    assert np.allclose(out[0][0], [0.25, 0, 10.25, 10]) and np.allclose(out[0][1], 0.25)


# ------------------------------------------------------------------------------------------ a real photograph
def test_a_face_is_found_in_a_photograph_with_468_landmarks_inside_its_box(astronaut):
    dets = detect_faces(astronaut)
    assert len(dets) == 1 and dets[0].score > 0.8
    x0, y0, x1, y1 = dets[0].box
    assert 150 < x0 < x1 < 300 and 50 < y0 < y1 < 200  # the astronaut's face
    face = find_face(astronaut)
    assert face.landmarks.shape == (468, 3) and face.presence > 0.9 and face.faces == 1
    # inside the face box (widened by 15% of its size: the mesh reaches the forehead, the box stops at the brows)
    mx, my = 0.15 * (x1 - x0), 0.15 * (y1 - y0)
    xy = face.landmarks[:, :2]
    assert ((xy[:, 0] > x0 - mx) & (xy[:, 0] < x1 + mx) & (xy[:, 1] > y0 - my) & (xy[:, 1] < y1 + my)).all()
    lm = face.landmarks
    # anatomy: eyes above the nose tip above the mouth; the subject's right eye on the image's left
    assert lm[33, 0] < lm[133, 0] < lm[362, 0] < lm[263, 0]
    assert max(lm[33, 1], lm[263, 1]) < lm[1, 1] < lm[13, 1] < lm[152, 1]
    # each iris centre lies between its eye's corners, its radius plausible for the eye's width
    for eye, (outer, inner) in enumerate(((33, 133), (263, 362))):
        centre = face.iris[eye, 0, :2]
        lo, hi = sorted((lm[outer, 0], lm[inner, 0]))
        assert lo < centre[0] < hi and abs(centre[1] - (lm[outer, 1] + lm[inner, 1]) / 2) < 4
        radius = np.linalg.norm(face.iris[eye, 1:, :2] - centre, axis=1).mean()
        assert 0.15 < radius / (hi - lo) < 0.4


def test_the_head_matte_keeps_the_head_and_drops_the_body(astronaut):
    face = find_face(astronaut)
    prob = person_probability(astronaut)
    assert prob.shape == (512, 512) and prob.dtype == np.float32
    matte = head_matte(prob, face.landmarks)
    nose = face.landmarks[POINTS["nose_tip"], :2].astype(int)
    assert prob[nose[1], nose[0]] > 0.9 and matte[nose[1], nose[0]] > 0.9
    assert prob[400, 100] > 0.9 and matte[400, 100] == 0.0  # the suit: a person, not the head
    assert prob[20, 20] < 0.1  # the flag behind


def test_the_head_matte_keeps_the_neck_but_not_the_shoulders_beside_it(astronaut):
    """Below the chin only a neck's width is kept (the selfie model paints shoulders, even under a floating head)."""
    face = find_face(astronaut)
    lm = face.landmarks[:, :2]
    chin_y, width = lm[:, 1].max(), lm[:, 0].max() - lm[:, 0].min()
    centre_x, height = (lm[:, 0].max() + lm[:, 0].min()) / 2, lm[:, 1].max() - lm[:, 1].min()
    prob = np.ones((512, 512), np.float32)  # a person everywhere: only the head's limits cut it
    matte = head_matte(prob, face.landmarks)
    below = int(chin_y + 0.1 * height)
    assert matte[below, int(centre_x)] > 0.99  # the neck under the chin
    assert matte[below, int(centre_x + 0.7 * width)] == 0.0 and matte[below, int(centre_x - 0.7 * width)] == 0.0
    above = int(chin_y - 0.3 * height)
    assert matte[above, int(centre_x + 0.7 * width)] > 0.99  # beside the face (ears, hair) stays
    assert matte[int(chin_y + 0.35 * height), int(centre_x)] == 0.0  # the chest


def test_the_mesh_silhouette_covers_the_projected_triangles_and_nothing_else():
    """A square of two triangles 2 m away through a 100 px focal length: pixels [40, 60) on both axes; at a larger
    size than max_side it is drawn coarse and scaled up, so it stays within a pixel of the scale of it."""
    vertices = np.array([[-0.2, -0.2, 2.0], [0.2, -0.2, 2.0], [0.2, 0.2, 2.0], [-0.2, 0.2, 2.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    sil = mesh_silhouette(vertices, faces, K, 100, 100)
    want = np.zeros((100, 100), bool)
    want[40:60, 40:60] = True
    assert sil.dtype == bool and sil.shape == (100, 100)
    assert sil[40:60, 40:60].all() and (sil & ~want).sum() <= 2 * 20 + 1  # at most the far edges' row and column
    big = mesh_silhouette(vertices, faces, K * np.array([[4], [4], [1]]), 400, 400, max_side=100)
    want_big = np.zeros((400, 400), bool)
    want_big[160:240, 160:240] = True
    assert big[164:236, 164:236].all() and not big[:156].any() and not big[244:].any()
    assert not big[:, :156].any() and not big[:, 244:].any()


def test_the_fitted_head_cuts_the_matte_to_the_head_and_its_hair(astronaut):
    """With the fitted head's silhouette the matte keeps hair above the head (within hair[0] face heights), only a
    margin beside the jaw and below the chin, and nothing far from the head, where the selfie model says person."""
    face = find_face(astronaut)
    lm = face.landmarks[:, :2]
    chin_y, top_y = lm[:, 1].max(), lm[:, 1].min()
    height = chin_y - top_y
    centre_x = (lm[:, 0].max() + lm[:, 0].min()) / 2
    sil = np.zeros((512, 512), bool)  # a stand-in head: the landmarks' box
    x0, x1, y0, y1 = (int(v) for v in (lm[:, 0].min(), lm[:, 0].max(), top_y, chin_y))
    sil[y0:y1, x0:x1] = True
    prob = np.ones((512, 512), np.float32)
    plain = head_matte(prob, face.landmarks)
    cut = head_matte(prob, face.landmarks, silhouette=sil)
    assert (cut <= plain).all() and cut[(y0 + y1) // 2, (x0 + x1) // 2] > 0.99
    assert cut[int(y0 - 0.2 * height), int(centre_x)] > 0.99  # hair above the head
    assert cut[int(y0 - 0.3 * height), int(centre_x)] == 0.0 < plain[int(y0 - 0.3 * height), int(centre_x)]
    beside_jaw = int(chin_y - 0.1 * height)
    assert cut[beside_jaw, int(x1 + 0.05 * height)] > 0.99 and cut[beside_jaw, int(x1 + 0.15 * height)] == 0.0
    below = int(chin_y + 0.1 * height)
    assert plain[below, int(centre_x)] > 0.99 and cut[below, int(centre_x)] == 0.0  # under the stand-in's chin


def test_a_soft_matte_becomes_a_coverage_with_a_one_pixel_edge():
    """A disc of radius 20 blurred over ~8 pixels (as the selfie model's probability is): sharpened, its 0.5 contour
    stays where it was, the soft rim shrinks to about the pixels the circle crosses, and its area (the summed matte)
    is the disc's within a pixel of perimeter; flat regions are 0 or 1."""
    yy, xx = np.mgrid[0:64, 0:64] + 0.5
    r = np.hypot(xx - 32.0, yy - 32.0)
    soft = (1.0 / (1.0 + np.exp((r - 20.0) / 2.0))).astype(np.float32)  # logistic rim, ~8 px from 0.1 to 0.9
    sharp = sharpen_edge(soft)
    assert sharp.dtype == np.float32 and sharp.shape == soft.shape
    rim = lambda m: int(((m > 0.02) & (m < 0.98)).sum())  # noqa: E731
    assert rim(soft) > 4 * rim(sharp) and rim(sharp) <= 2.5 * 2 * np.pi * 20
    assert np.array_equal(sharp > 0.5, soft > 0.5)
    assert abs(float(sharp.sum()) - np.pi * 20 ** 2) < 2 * np.pi * 20 * 0.25
    assert sharp[32, 32] == 1.0 and sharp[0, 0] == 0.0
    faint = np.full((16, 16), 0.3, np.float32)  # a flat faint plateau is background, a strong one head
    assert (sharpen_edge(faint) == 0).all() and (sharpen_edge(faint + 0.5) == 1).all()


def test_no_face_is_a_named_error():
    blank = np.full((256, 256, 3), 90, np.uint8)
    with pytest.raises(TrackingError) as e:
        find_face(blank)
    assert e.value.field == "face"
    with pytest.raises(TrackingError) as e:
        track_landmarks([blank] * 3)
    assert e.value.field == "face" and "3 frames" in str(e.value)


def test_the_largest_of_several_faces_is_tracked_and_reported(astronaut):
    from render_core.tracking.geometry import resize

    face = astronaut[30:250, 115:335]  # 220 x 220 around the face
    small = np.round(resize(face, 154, 154)).astype(np.uint8)  # the same face at 70%
    canvas = np.full((240, 414, 3), 128, np.uint8)
    canvas[20:174, 10:164] = small
    canvas[10:230, 184:404] = face  # the larger one on the right
    found = find_face(canvas)
    assert found.faces == 2
    assert found.box[0] > 184  # the larger face
    track = track_landmarks([canvas, canvas, canvas], detect_every=1)
    assert track.report()["max_faces"] == 2 and track.report()["frames_with_several_faces"] == 3
    assert (track.boxes[:, 0] > 184).all()


# ------------------------------------------------------------------------------------- the synthetic head video
@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """`blendsplat data synth --frames 12 --size 256 --seed 3`, its frames, tracking and the open head."""
    from render_core.data.generate import synth_dataset
    from render_core.data.portable import read_dataset
    from render_core.facemodel.open_head import open_head

    folder = tmp_path_factory.mktemp("synth") / "ds"
    synth_dataset(folder, frames=12, size=256, seed=3)
    ds = read_dataset(folder)
    frames = [np.asarray(ds.frame(i)) for i in range(len(ds))]
    frames = [f if f.dtype == np.uint8 else np.round(f * 255).astype(np.uint8) for f in frames]
    return frames, ds.tracking, open_head()


def _project(vertices: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    cam = vertices @ R.T + t
    uv = cam @ K.T
    return uv[..., :2] / uv[..., 2:3]


def _correspondence(model) -> tuple[dict[str, int], dict[str, float]]:
    """MediaPipe point -> open-head vertex: the nearest visible projected vertex to the landmark found on a neutral
    frame (no expression, front view), and that distance in pixels."""
    from render_core.data.albedo import SkinAlbedo
    from render_core.data.generate import make_script, render_frames, script_cameras
    from render_core.data.meshraster import rasterize
    from render_core.rotation import axis_angle_to_matrix

    script = make_script(model, 2, 3)
    for x in (script.expression, script.joint_rotations, script.eyelids, script.head):
        x.zero_()
    cams = script_cameras(model, script, 256)
    rgb, _ = next(render_frames(model, script, cams, SkinAlbedo(model, 3)))
    with torch.no_grad():
        posed, _ = model.evaluate(script.expression[:1], axis_angle_to_matrix(script.joint_rotations[:1]),
                                  script.eyelids[:1], script.shape)
    face_id = rasterize(posed, model.faces, cams.index(slice(0, 1))).face_id[0]
    visible = model.faces[face_id[face_id >= 0].unique()].unique().numpy()
    uv = _project(posed[0].double().numpy(), *(x[0].double().numpy() for x in (cams.K, cams.R, cams.t)))
    landmarks = find_face(rgb).landmarks
    vertex, residual = {}, {}
    for name in COMPARED:
        d = np.linalg.norm(uv[visible] - landmarks[POINTS[name], :2], axis=1)
        vertex[name], residual[name] = int(visible[d.argmin()]), float(d.min())
    return vertex, residual


def test_landmarks_follow_the_synthetic_heads_known_vertices(synthetic):
    from render_core.rotation import axis_angle_to_matrix

    frames, tracking, model = synthetic
    vertex, residual = _correspondence(model)
    assert max(residual.values()) < 1.5  # the mesh's point has a vertex of the open head within 1.5 px
    track = track_landmarks(frames)
    assert track.status.count("detected") >= 1 and track.report()["kept"] == 12
    with torch.no_grad():
        posed, _ = model.evaluate(torch.from_numpy(tracking.expression),
                                  axis_angle_to_matrix(torch.from_numpy(tracking.joint_rotations)),
                                  torch.from_numpy(tracking.eyelids), torch.from_numpy(tracking.shape))
    errors = {}
    for name in COMPARED:
        truth = np.stack([_project(posed[i, vertex[name]].double().numpy(), tracking.K[i].astype(np.float64),
                                   tracking.R[i].astype(np.float64), tracking.t[i].astype(np.float64))
                          for i in range(len(frames))])
        errors[name] = np.linalg.norm(track.landmarks[:, POINTS[name], :2] - truth, axis=1)
    every = np.concatenate(list(errors.values()))
    print("median pixel error at 256x256:", {k: round(float(np.median(v)), 2) for k, v in errors.items()},
          "all:", round(float(np.median(every)), 2))
    # Measured: 1.4 px median over the 84 points (face about 110 px wide). The synthetic blink (frames 6-8, a
    # flat closed lid) throws MediaPipe's eye corners off by up to 17 px; everything else stays within 4 px.
    assert np.median(every) < 2.0
    for name in ("nose_tip", "mouth_right", "mouth_left"):
        assert errors[name].max() < 5.0, (name, errors[name])


def test_short_gaps_are_interpolated_and_long_ones_dropped_with_reasons(synthetic):
    frames = synthetic[0]
    blank = np.zeros_like(frames[0])
    video = [frames[0], frames[1], blank, frames[2], frames[3], blank, blank, blank, blank, frames[4], blank]
    track = track_landmarks(video, max_gap=2)
    assert track.status == ["detected", "tracked", "interpolated", "detected", "tracked", "dropped", "dropped",
                            "dropped", "dropped", "detected", "dropped"]
    report = track.report()
    assert (report["kept"], report["interpolated"], report["dropped"]) == (6, 1, 5)
    assert [(r["start"], r["end"]) for r in report["dropped_runs"]] == [(5, 8), (10, 10)]
    assert "lost for 4 frames" in report["dropped_runs"][0]["reason"]
    assert "last seen" in report["dropped_runs"][1]["reason"]
    assert np.allclose(track.landmarks[2], (track.landmarks[1] + track.landmarks[3]) / 2)
    assert np.isnan(track.landmarks[5]).all() and np.isnan(track.boxes[10]).all()
    assert list(track.kept) == [0, 1, 2, 3, 4, 9]
    late = track_landmarks([blank, frames[0]], max_gap=2)
    assert late.dropped == [(0, 0, "before the face was first found")]


def test_irises_found_beside_the_tracker_are_those_found_in_turn(synthetic):
    frames = synthetic[0]
    serial, pipelined = track_landmarks(frames, threads=1), track_landmarks(frames, threads=2)
    assert serial.status == pipelined.status and not np.isnan(pipelined.iris).any()
    assert np.array_equal(serial.landmarks, pipelined.landmarks) and np.array_equal(serial.iris, pipelined.iris)


def test_the_tracker_redetects_a_lost_face(synthetic):
    frames = synthetic[0]

    def placed(frame: np.ndarray, y: int, x: int) -> np.ndarray:
        canvas = np.zeros((512, 512, 3), np.uint8)
        canvas[y:y + 256, x:x + 256] = frame
        return canvas

    tracker = FaceTracker()
    assert tracker.step(placed(frames[0], 0, 0)).source == "detected"
    assert tracker.step(placed(frames[1], 0, 0)).source == "tracked"
    # the head jumps across the frame: the previous crop holds no face, the detector finds it again in this frame
    found = tracker.step(placed(frames[2], 256, 256))
    assert found is not None and found.source == "detected" and found.box[0] > 256 and found.box[1] > 256
    assert tracker.step(placed(frames[3], 256, 256)).source == "tracked"
    with pytest.raises(TrackingError):
        FaceTracker(detector="huge")


def test_the_matte_dilation_is_a_square_max_filter_at_any_radius():
    """The running-maximum dilation (time independent of the radius) equals a square max-pool, edges included."""
    from render_core.tracking.segment import _dilated

    rng = np.random.default_rng(0)
    mask = rng.random((130, 97)) > 0.99
    mask[0, 5] = mask[129, 96] = True  # at the edges
    for radius in (0, 1, 2, 3, 4, 17, 70):
        want = torch.nn.functional.max_pool2d(torch.from_numpy(mask.astype(np.float32))[None, None],
                                              2 * radius + 1, stride=1, padding=radius)[0, 0].numpy() > 0.5
        got = _dilated(mask, radius)
        assert got.dtype == bool and np.array_equal(got, want), radius


def _disk(size: int, centre: tuple[float, float], radius: float) -> np.ndarray:
    y, x = np.mgrid[:size, :size] + 0.5
    return (x - centre[0]) ** 2 + (y - centre[1]) ** 2 <= radius ** 2


def test_the_colour_cut_drops_spill_that_looks_like_the_background_and_keeps_hair():
    """Outside the fitted head, the matte gives up what has the colour of the background beside it (the selfie
    model's spill beside a head on a plain wall) and keeps what does not (hair); inside the head it stays."""
    from render_core.tracking.segment import colour_cut

    size, height = 128, 40.0
    head = _disk(size, (64, 70), 24)
    spill = _disk(size, (64, 70), 34)  # what the selfie model calls person: the head and a ring around it
    hair = spill & ~head & (np.mgrid[:size, :size][0] < 50)  # above the head, inside the ring
    rgb = np.empty((size, size, 3), np.uint8)
    rgb[:] = (40, 60, 90)  # a blue-grey wall
    rgb[head] = (200, 150, 120)  # skin
    rgb[hair] = (90, 50, 20)  # brown hair
    noise = np.random.default_rng(0).integers(-4, 5, rgb.shape)  # sensor noise
    rgb = np.clip(rgb + noise, 0, 255).astype(np.uint8)
    matte = spill.astype(np.float32)
    cut = colour_cut(matte, rgb, head, height)
    assert (cut <= matte).all() and np.array_equal(cut[head], matte[head])  # only takes away; the head untouched
    ring = spill & ~head & ~hair
    assert cut[ring].max() == 0.0 and cut[hair].min() == 1.0
    assert np.array_equal(cut[~spill], matte[~spill])  # nothing added
    # the fitted head a little too large (the fit's error): the wall inside its edge goes too, the skin stays
    assert np.array_equal(colour_cut(matte, rgb, _disk(size, (64, 70), 25), height), cut)
    # the whole frame inside the fitted head: the matte as it was
    assert np.array_equal(colour_cut(matte, rgb, np.ones_like(head), height), matte)


def test_the_colour_cut_takes_the_backgrounds_colour_from_the_pixels_it_is_given():
    """Hair past the matte's hair margin is not the wall: given as background, it would make the hair inside the
    margin look like background; ``head_matte`` leaves it out of the background's colour."""
    from render_core.tracking.segment import colour_cut

    size, height = 128, 40.0
    head = _disk(size, (64, 70), 24)
    hair = _disk(size, (64, 60), 40) & ~head & (np.mgrid[:size, :size][0] < 60)  # a big head of hair
    rgb = np.empty((size, size, 3), np.uint8)
    rgb[:] = (40, 60, 90)
    rgb[head], rgb[hair] = (200, 150, 120), (90, 50, 20)
    matte = _disk(size, (64, 70), 34).astype(np.float32)  # the hair margin cut the hair's top off
    near = hair & (matte > 0)
    wrong = colour_cut(matte, rgb, head, height)  # the cut-off hair counted as background
    right = colour_cut(matte, rgb, head, height, background=(matte < 0.02) & ~hair)
    assert wrong[near].mean() < 0.5 and right[near].min() == 1.0
