"""The HTTP API's response models (avatars, adapters, operations); the error model is :mod:`service.openapi`'s.

Their names are the OpenAPI document's schema names: renaming one changes the published contract."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from blendsplat.v1 import render_pb2 as pb

from ..engine import AVATAR_ID_PATTERN


# ------------------------------------------------------------------------------------------------------- avatars
class AvatarOut(BaseModel):
    """An avatar as REST answers it: blendsplat.v1.AvatarInfo with its proto field names and plain numbers."""

    id: str
    loaded: bool = Field(description="in this replica's cache")
    gaussians: int = Field(description="face + mouth")
    mouth_gaussians: int
    expression_names: list[str]
    joint_names: list[str]
    sh_degree: int
    precision: str = Field(description="blendshape storage: fp32 or fp16")
    face_model: str
    file_bytes: int
    memory_bytes: int = Field(description="resident in this replica's cache (0 when not loaded)")
    digest: str = Field(description="sha256 of the bundle's content")
    trained: bool = Field(description="learned from a video by the training pipeline (its provenance records the "
                                      "dataset, preset and iterations)")
    psnr_head: float | None = Field(description="a trained avatar's head-mask PSNR on its dataset's held-out "
                                                "frames, dB; null when it has none")

    @classmethod
    def of(cls, info: pb.AvatarInfo) -> AvatarOut:
        return cls(**{name: getattr(info, name) if name != "psnr_head" or info.HasField(name) else None
                      for name in cls.model_fields})


class AvatarList(BaseModel):
    avatars: list[AvatarOut]


# ------------------------------------------------------------------------------------------------------ adapters
class AdapterSource(BaseModel):
    convention: str = Field(description="the source's naming: arkit-52, flame, mediapipe-52, live-link-face or "
                                        "custom")
    face_model: str = Field(description="the tracker's face model, or empty")
    names: list[str] = Field(description="the model's inputs in order: expression names, and <joint>.x/.y/.z for a "
                                         "source joint's axis-angle components")


Bound = float | Literal["inf", "-inf"]  # JSON has no infinity


class AdapterTarget(BaseModel):
    face_model: str = Field(description="the avatars it drives have this face model")
    expression_names: list[str]
    joint_names: list[str]
    expression_min: list[Bound] | None = Field(description="the clamp the model applies, per target expression")
    expression_max: list[Bound] | None


class AdapterManifestOut(BaseModel):
    """The adapter manifest (docs/method.md section 12)."""

    format: Literal["blendsplat-adapter"]
    version: int
    id: str
    source: AdapterSource
    target: AdapterTarget
    opset: int
    provenance: dict[str, Any] = Field(description="how it was made (free-form)")


class AdapterOut(BaseModel):
    id: str
    tenant: str | None = Field(description="the owning tenant; null: the deployment's (every key may use it)")
    model_bytes: int
    model_sha256: str
    manifest: AdapterManifestOut


class AdapterList(BaseModel):
    adapters: list[AdapterOut]


# ------------------------------------------------------------------------------------------------ session tokens
class TokenRequest(BaseModel):
    """The body of ``POST /v1/tokens``."""

    model_config = ConfigDict(extra="forbid")

    avatar: str | None = Field(None, max_length=128, pattern=AVATAR_ID_PATTERN.pattern,
                               description="the one avatar the token may read and stream; null: any its tenant may")
    expires_in: int = Field(600, ge=1, description="seconds the token lives (at most the setting token_max_seconds, "
                                                   "3600 by default)")


class TokenOut(BaseModel):
    token: str = Field(description="bst.<payload>.<signature>: send it as 'Authorization: Bearer <token>' or as the "
                                   "WebSocket subprotocol bearer.<token>")
    expires_at: int = Field(description="unix seconds")
    scope: Literal["render"]
    avatar: str | None
    tenant: str


# ---------------------------------------------------------------------------------------------------- operations
class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    ready: bool
    checks: dict[str, bool] = Field(description="each readiness check by name (settings, bundle_store, warm_up, "
                                               "not_draining, job_database...)")
    reasons: dict[str, str] | None = Field(None, description="when not ready: why, for each failing check")
