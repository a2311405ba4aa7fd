"""Dataset frames as render inputs and targets: what training and evaluation both need.

The tracking of frame i gives the avatar's animation parameters (expression by name, joint rotations, eyelids)
and the camera; the target is the frame with its background masked to black (the paper's protocol) plus the head
mask. Expressions are matched by name, so a dataset whose expression order differs from the avatar's still works.
"""

from __future__ import annotations

import numpy as np
import torch

from ..avatar import Avatar
from ..camera import Cameras
from ..deform import Frame
from ..errors import DatasetError
from .portable import Dataset, Tracking


def check_compatible(avatar: Avatar, tracking: Tracking) -> None:
    """DatasetError unless the tracking animates this avatar (the same expression and joint names)."""
    if sorted(tracking.expression_names) != sorted(avatar.expression_names):
        raise DatasetError(f"the dataset's expressions ({len(tracking.expression_names)}) are not the avatar's "
                           f"({len(avatar.expression_names)}); was the avatar made from another face model?",
                           field="expression_names")
    if list(tracking.joint_names) != list(avatar.joint_names):
        raise DatasetError(f"joints {tracking.joint_names} are not the avatar's {avatar.joint_names}",
                           field="joint_names")


def frame_inputs(avatar: Avatar, tracking: Tracking, indices: list[int] | np.ndarray) -> tuple[Frame, Cameras]:
    """B frames (by dataset index) as a Frame of the avatar and their B cameras."""
    idx = np.asarray(indices, dtype=np.int64)
    order = [tracking.expression_names.index(n) for n in avatar.expression_names]
    expression = torch.from_numpy(np.ascontiguousarray(tracking.expression[idx][:, order]))
    joints = torch.from_numpy(np.ascontiguousarray(tracking.joint_rotations[idx]))
    eyelids = torch.from_numpy(np.ascontiguousarray(tracking.eyelids[idx]))
    frame = Frame.from_params(avatar, expression=expression, joints=joints,
                              eyelids=eyelids if bool(eyelids.abs().sum()) else None)
    cams = Cameras(torch.from_numpy(tracking.K[idx]).float(), torch.from_numpy(tracking.R[idx]).float(),
                   torch.from_numpy(tracking.t[idx]).float(), int(tracking.width), int(tracking.height))
    return frame, cams


def targets(dataset: Dataset, indices: list[int] | np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """RGB [B, H, W, 3] with the background masked to black, and the head masks [B, H, W], in [0, 1]."""
    rgb, masks = [], []
    for i in np.asarray(indices, dtype=np.int64).tolist():
        mask = torch.from_numpy(dataset.mask(i))
        rgb.append(torch.from_numpy(dataset.frame(i)) * mask[..., None])
        masks.append(mask)
    return torch.stack(rgb), torch.stack(masks)
