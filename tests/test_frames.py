"""Dataset frames as render inputs: an avatar initialised on the data's face model lines up with its masks."""

from __future__ import annotations

import pytest

from render_core.data import read_dataset
from render_core.data.frames import check_compatible, frame_inputs, targets
from render_core.data.generate import synth_dataset
from render_core.errors import DatasetError
from render_core.renderer import AvatarRenderer
from render_core.tools.synth import synth_avatar
from render_core.train.initialize import init_avatar


def test_initialised_avatar_matches_the_synthetic_masks(head, tmp_path):
    synth_dataset(tmp_path / "ds", frames=4, size=64, seed=1, facemodel=head)
    ds = read_dataset(tmp_path / "ds")
    avatar = init_avatar(head, gaussians=6000, mouth=100, opacity=0.95, seed=0)
    check_compatible(avatar, ds.tracking)
    frame, cams = frame_inputs(avatar, ds.tracking, [0, 3])
    rgb, mask = targets(ds, [0, 3])
    out = AvatarRenderer(avatar).render(frame, cams)
    assert rgb.shape == out.rgb.shape and mask.shape == out.alpha.shape
    covered = out.alpha > 0.5
    iou = float((covered & (mask > 0.5)).sum() / (covered | (mask > 0.5)).sum())
    assert iou > 0.8  # the same pose, camera and silhouette
    assert float(rgb[mask == 0].abs().max()) == 0.0  # background masked to black
    with pytest.raises(DatasetError, match="expression"):
        check_compatible(synth_avatar(gaussians=50, blendshapes=3), ds.tracking)
