"""A procedural skin albedo with real high-frequency detail, and Lambert shading, for ``data synth``.

The albedo is a function of the REST (canonical) surface position of a face model, so the texture sticks to the
skin whatever the expression or pose: the renderer interpolates :meth:`SkinAlbedo.vertex_attributes` (rest
position and material weights per vertex) perspective-correctly and calls :class:`SkinAlbedo` per pixel. Layers:

- base skin tone with smooth variation (2-5 cm noise, redder cheeks and nose);
- mottling at 1-8 mm and pores (dark dots where a 0.7 mm noise peaks; resolved from about 512 px up);
- freckles: ~4000 round brown dots (1-2.5 mm) scattered on the skin, denser on the front of the face, patchy, and
  denser on the subject's LEFT (+x) side; plus distinct marks on the LEFT side only: 30 darker spots and two moles
  on the cheek, nose side and temple (seeded positions);
- darker eyebrows: arched bands above the eyes, with hair strokes;
- redder lips (an ellipse around the mouth with vertical lip lines); the mouth interior (skin near the mouth that
  no front-ish view sees in the rest pose) dark red;
- eyeball vertex groups (``eyeball_*``): off-white sclera, textured iris (limbal ring, radial fibres), black pupil,
  facing the rest +z axis; ``teeth*`` groups near-white; ``tongue`` pink.

Landmarks come from the model: eye centres from the eyeball groups (else the ``eye_l``/``eye_r`` joints, else a
guess from the bounding box), the mouth from the displacement of the ``mouth*`` expression bases (else a point one
eye distance below the eyes), snapped to the front surface; sizes scale with the eye distance.

Noise is band-limited: sums of random sinusoids (:class:`SpectralNoise`, random Fourier features) and Gaussian dots
looked up through a grid (:class:`DotField`), all seeded (no global RNG state). Anti-aliasing: every layer is
prefiltered by the pixel footprint (metres per pixel, per pixel): each sinusoid is attenuated by a Gaussian of half
a pixel and each dot widened by it (energy preserving), so a detail the camera cannot resolve fades instead of
flickering from frame to frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..camera import Cameras, look_at
from ..facemodel.model import FaceModel
from .meshraster import rasterize

__all__ = ["ALBEDO_CHANNELS", "DotField", "FaceLandmarks", "SkinAlbedo", "SpectralNoise", "face_landmarks", "lambert"]

ALBEDO_CHANNELS = 7  # rest position (3), eyeball / teeth / tongue / mouth-interior weights (4)
LIGHT = (-0.35, 0.45, 0.82)  # towards the light, in the face model's frame (y up, face towards +z)
AMBIENT, DIFFUSE = 0.32, 0.75
PREFILTER = 0.5  # Gaussian prefilter sigma, in pixel footprints (about one pixel's box)
FRECKLE_SPACING = 0.0038  # mean distance between freckle dots on the densest skin, metres
FRECKLE_SIGMA = (0.00045, 0.0010)  # Gaussian radius range of a freckle dot, metres

SKIN = (0.80, 0.59, 0.48)
BROW = (0.20, 0.13, 0.09)
LIPS = (0.74, 0.38, 0.37)
MOUTH_INSIDE = (0.38, 0.12, 0.12)
FRECKLE = (0.52, 0.32, 0.22)
MOLE = (0.28, 0.16, 0.11)
SCLERA = (0.86, 0.82, 0.78)
PUPIL = (0.03, 0.03, 0.03)
IRISES = ((0.36, 0.22, 0.11), (0.30, 0.42, 0.50), (0.32, 0.34, 0.18))  # brown, blue-grey, hazel
TEETH = (0.92, 0.89, 0.80)
TONGUE = (0.80, 0.42, 0.44)


class SpectralNoise:
    """Band-limited noise from random Fourier features: a sum of ``waves`` sinusoids per octave with random
    directions, phases and frequencies (within +-30% of the octave's), each attenuated by a Gaussian prefilter of
    the pixel footprint. Zero mean; the standard deviation of an unfiltered octave is its amplitude.

    An octave of ``spacing`` metres has a wavelength of about two spacings (the feature size is one spacing);
    ``stretch`` scales the frequency per axis (0.1 along x: features ten times longer along x)."""

    def __init__(self, spacings: tuple[float, ...], amplitudes: tuple[float, ...], seed: int, waves: int = 16,
                 stretch: tuple[float, float, float] = (1.0, 1.0, 1.0)):
        g = torch.Generator().manual_seed(int(seed) * 1_000_003 + 12345)
        omegas, phases, amps = [], [], []
        for spacing, amp in zip(spacings, amplitudes, strict=True):
            d = torch.nn.functional.normalize(torch.randn(waves, 3, generator=g, dtype=torch.float64), dim=-1)
            f = (math.pi / spacing) * (0.7 + 0.6 * torch.rand(waves, generator=g, dtype=torch.float64))
            omegas.append(d * f[:, None] * torch.tensor(stretch, dtype=torch.float64))
            phases.append(2 * math.pi * torch.rand(waves, generator=g, dtype=torch.float64))
            amps.append(torch.full((waves,), amp * math.sqrt(2.0 / waves), dtype=torch.float64))
        self.omega = torch.cat(omegas).float()  # [M, 3] radians per metre
        self.phase = torch.cat(phases).float()  # [M]
        self.amp = torch.cat(amps).float()  # [M]
        self.omega2 = (self.omega.double() ** 2).sum(-1).float()  # [M]

    def __call__(self, p: Tensor, footprint: Tensor | None = None) -> Tensor:
        """Noise [N] (float32) at points p [N, 3] (metres); ``footprint`` [N]: pixel size in metres (None: none)."""
        if p.shape[0] == 0:
            return torch.zeros(0)
        keep = torch.ones(self.amp.shape[0], dtype=torch.bool)
        if footprint is not None:  # drop waves that the prefilter removes everywhere
            s2 = float((PREFILTER * footprint.min()) ** 2)
            keep = (-0.5 * s2 * self.omega2) > -7.0
            if not bool(keep.any()):
                return torch.zeros(p.shape[0])
        omega, phase, amp, om2 = self.omega[keep], self.phase[keep], self.amp[keep], self.omega2[keep]
        wave = torch.sin(p.float() @ omega.T + phase)  # [N, M]
        if footprint is None:
            return wave @ amp
        sigma2 = (PREFILTER * footprint.float()) ** 2
        atten = torch.exp(-0.5 * sigma2[:, None] * om2[None])
        return (wave * atten) @ amp


class DotField:
    """Round Gaussian dots (centres [D, 3], radii [D], strengths [D]; metres), summed at query points through a
    uniform grid: every dot is listed in the (at most 8) cells its 3.5-sigma ball touches, so a point only looks at
    the dots of its own cell. Each dot is prefiltered by the pixel footprint (energy preserving)."""

    def __init__(self, centres: Tensor, sigma: Tensor, strength: Tensor, max_per_cell: int = 32):
        self.centres, self.sigma, self.strength = centres.float(), sigma.float(), strength.float()
        self.cell = max(3.5 * float(sigma.max()) if sigma.numel() else 0.0, 0.004)
        if centres.shape[0] == 0:
            self.keys = torch.zeros(0, dtype=torch.int64)
            self.table = torch.zeros(0, 1, dtype=torch.int64)
            return
        reach = 3.5 * self.sigma[:, None]
        lo = torch.floor((self.centres - reach) / self.cell).long()
        hi = torch.floor((self.centres + reach) / self.cell).long()
        keys, dots = [], []
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    cell = lo + torch.tensor([dx, dy, dz])
                    ok = (cell <= hi).all(-1)
                    keys.append(self._pack(cell[ok]))
                    dots.append(torch.nonzero(ok).squeeze(1))
        key, dot = torch.cat(keys), torch.cat(dots)
        order = torch.argsort(key * (len(centres) + 1) + dot)  # by cell, then dot: deterministic
        key, dot = key[order], dot[order]
        self.keys, inverse, counts = torch.unique_consecutive(key, return_inverse=True, return_counts=True)
        rank = torch.arange(key.numel()) - (torch.cumsum(counts, 0) - counts)[inverse]
        width = min(int(counts.max()), max_per_cell)
        self.table = torch.full((self.keys.numel(), width), -1, dtype=torch.int64)
        ok = rank < width
        self.table[inverse[ok], rank[ok]] = dot[ok]

    @staticmethod
    def _pack(cell: Tensor) -> Tensor:
        c = cell + (1 << 20)
        return (c[..., 0] << 42) | (c[..., 1] << 21) | c[..., 2]

    def __call__(self, p: Tensor, footprint: Tensor | None = None) -> Tensor:
        """Sum of the dots' strengths x Gaussian falloff at points p [N, 3] -> [N]."""
        out = torch.zeros(p.shape[0])
        if self.keys.numel() == 0 or p.shape[0] == 0:
            return out
        key = self._pack(torch.floor(p.float() / self.cell).long())
        slot = torch.searchsorted(self.keys, key).clamp_max(self.keys.numel() - 1)
        hit = torch.nonzero(self.keys[slot] == key).squeeze(1)
        if hit.numel() == 0:
            return out
        cand = self.table[slot[hit]]  # [n, W]
        valid = cand >= 0
        cand = cand.clamp_min(0)
        d2 = ((p[hit, None, :].float() - self.centres[cand]) ** 2).sum(-1)
        sig2 = self.sigma[cand] ** 2
        eff2 = sig2 if footprint is None else sig2 + (PREFILTER * footprint[hit, None].float()) ** 2
        a = self.strength[cand] * (sig2 / eff2) * torch.exp(-d2 / (2 * eff2))
        out[hit] = (a * valid).sum(-1)
        return out


def _smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _rgb(c: tuple[float, float, float]) -> Tensor:
    return torch.tensor(c, dtype=torch.float32)


@dataclass
class FaceLandmarks:
    """Rest-pose landmarks (metres, the model's frame) that place the albedo's regions."""

    eye_l: Tensor  # [3] centre of the subject's left eyeball (+x)
    eye_r: Tensor  # [3]
    eye_radius: float
    mouth: Tensor  # [3] centre of the lips, on the front surface
    iod: float  # distance between the eye centres


def _group(model: FaceModel, *keys: str) -> Tensor:
    idx = [v for name, v in model.vertex_groups.items() if any(k in name.lower() for k in keys)]
    return torch.cat(idx).unique() if idx else torch.zeros(0, dtype=torch.int64)


def face_landmarks(model: FaceModel) -> FaceLandmarks:
    """Eyes, mouth and scale of ``model``'s rest template (see the module docstring for the fallbacks)."""
    t = model.template.to(torch.float64)
    groups = {k.lower(): v for k, v in model.vertex_groups.items()}
    eyes = []
    for side, joint in (("l", "eye_l"), ("r", "eye_r")):
        g = groups.get(f"eyeball_{side}")
        if g is not None and g.numel():
            eyes.append(t[g].mean(0))
        elif joint in model.joint_names:
            eyes.append(model.joint_positions[model.joint_names.index(joint)].to(torch.float64))
        else:  # a human-proportioned guess: eyes a third of the way down from the top, 3 cm apart from the middle
            lo, hi = t.min(0).values, t.max(0).values
            centre = (lo + hi) / 2
            eyes.append(torch.stack([centre[0] + (0.031 if side == "l" else -0.031), hi[1] - 0.35 * (hi[1] - lo[1]),
                                     hi[2] - 0.025]))
    eye_l, eye_r = eyes
    if eye_l[0] < eye_r[0]:
        eye_l, eye_r = eye_r, eye_l
    iod = float((eye_l - eye_r).norm())
    g = groups.get("eyeball_l")
    eye_radius = float((t[g] - eye_l).norm(dim=-1).mean()) if g is not None and g.numel() else 0.19 * iod

    interior = _group(model, "eyeball", "teeth", "tongue")
    skin = torch.ones(t.shape[0], dtype=torch.bool)
    skin[interior] = False
    mid_eye = (eye_l + eye_r) / 2
    names = [(i, n) for i, n in enumerate(model.expression_names) if n.lower().startswith("mouth")
             and n != "mouthClose"]
    mouth = None
    if names:
        w = sum(model.expression_basis[i].to(torch.float64).norm(dim=-1) ** 2 for i, _ in names)
        w = torch.where(skin & (t[:, 1] < mid_eye[1]), w, torch.zeros_like(w))
        if float(w.sum()) > 0:
            top = w.topk(min(200, int((w > 0).sum()))).indices
            mouth = (t[top] * w[top, None]).sum(0) / w[top].sum()
    if mouth is None:
        mouth = mid_eye - torch.tensor([0.0, 1.05 * iod, 0.0], dtype=torch.float64)
    # Snap to the front surface: the most forward skin vertex near the mouth's (x, y).
    near = skin & ((t[:, 0] - mouth[0]).abs() < 0.12 * iod) & ((t[:, 1] - mouth[1]).abs() < 0.12 * iod)
    if bool(near.any()):
        mouth = torch.stack([mouth[0], mouth[1], t[near, 2].max()])
    return FaceLandmarks(eye_l.float(), eye_r.float(), eye_radius, mouth.float(), iod)


def _front_visible(model: FaceModel, size: int = 192) -> Tensor:
    """[V] bool: vertices of triangles visible in the rest pose from five front-ish views (the mouth closed)."""
    t = model.template.float()
    lo, hi = t.min(0).values, t.max(0).values
    centre = (lo + hi) / 2
    extent = float((hi - lo).max())
    dist = 4.0 * extent
    views = [(0.0, 0.0), (30.0, 0.0), (-30.0, 0.0), (0.0, 20.0), (0.0, -20.0)]
    eyes = torch.stack([centre + dist * torch.tensor([math.sin(math.radians(y)) * math.cos(math.radians(p)),
                                                      math.sin(math.radians(p)),
                                                      math.cos(math.radians(y)) * math.cos(math.radians(p))])
                        for y, p in views])
    R, tr = look_at(eyes, centre.expand_as(eyes))
    f = 0.9 * size * dist / extent
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]]).expand(len(views), 3, 3)
    frags = rasterize(t[None].expand(len(views), -1, -1), model.faces, Cameras(K.clone(), R, tr, size, size))
    ids = frags.face_id[frags.face_id >= 0].unique()
    visible = torch.zeros(t.shape[0], dtype=torch.bool)
    visible[model.faces[ids].flatten()] = True
    return visible


class SkinAlbedo:
    """The procedural albedo of one face model and seed: ``SkinAlbedo(model, seed)(attrs, footprint)`` -> RGB.

    ``attrs`` [N, 7] are per-pixel interpolations of :meth:`vertex_attributes`; ``footprint`` [N] (or a float) is
    the pixel size on the surface in metres (camera depth / focal length), 0 for no prefiltering.
    """

    def __init__(self, model: FaceModel, seed: int = 0):
        self.model = model
        self.seed = s = int(seed)
        self.landmarks = lm = face_landmarks(model)
        iod = lm.iod
        g = torch.Generator().manual_seed(s * 7919 + 17)
        self.iris = IRISES[int(torch.randint(len(IRISES), (1,), generator=g))]
        # Noise layers (metres): tone and redness (cm), mottling (1-10 mm), pores (0.7 mm), lip lines, brow hair...
        self.tone = SpectralNoise((0.045, 0.022), (0.05, 0.035), s + 1, waves=8)
        self.red = SpectralNoise((0.03,), (0.05,), s + 2, waves=8)
        self.mottle = SpectralNoise((0.008, 0.004, 0.002, 0.001), (0.035, 0.04, 0.045, 0.04), s + 3, waves=24)
        self.freckle_density = SpectralNoise((0.02,), (0.5,), s + 14, waves=8)
        self.chroma = SpectralNoise((0.005, 0.0025), (0.03, 0.03), s + 4, waves=12)
        self.pores = SpectralNoise((0.0007,), (1.0,), s + 5, waves=24)
        self.lip_lines = SpectralNoise((0.012 * iod, 0.006 * iod), (0.10, 0.08), s + 6, waves=12,
                                       stretch=(1.0, 0.15, 1.0))
        self.hair = SpectralNoise((0.008 * iod, 0.004 * iod), (0.30, 0.25), s + 7, waves=16,
                                  stretch=(0.15, 1.0, 1.0))
        self.brow_patch = SpectralNoise((0.05 * iod,), (0.15,), s + 8, waves=8)
        self.iris_fibres = SpectralNoise((0.06 * lm.eye_radius, 0.03 * lm.eye_radius), (0.22, 0.15), s + 9,
                                         waves=12, stretch=(1.0, 0.25, 1.0))
        self.veins = SpectralNoise((0.2 * lm.eye_radius, 0.1 * lm.eye_radius), (0.05, 0.04), s + 10, waves=8)
        self.teeth_var = SpectralNoise((0.05 * iod, 0.02 * iod), (0.04, 0.03), s + 11, waves=8,
                                       stretch=(1.0, 0.3, 1.0))
        self.tongue_bumps = SpectralNoise((0.03 * iod, 0.012 * iod), (0.08, 0.06), s + 12, waves=8)

        t = model.template.to(torch.float64)
        groups = _group(model, "eyeball", "teeth", "tongue")
        skin = torch.ones(t.shape[0], dtype=torch.bool)
        skin[groups] = False
        # The mouth interior: skin near the mouth that no front-ish view sees in the rest pose (mouth closed).
        m = lm.mouth.to(torch.float64)
        near_mouth = (((t[:, 0] - m[0]) / (0.6 * iod)) ** 2 + ((t[:, 1] - m[1]) / (0.45 * iod)) ** 2 < 1.0)
        near_mouth &= t[:, 2] < m[2] + 0.05 * iod
        self.inside = skin & near_mouth & ~_front_visible(model)
        self.freckles = self._scatter_freckles(skin & ~self.inside, g)
        # Distinct marks on the subject's left (+x) side only: spots and moles on the cheek, nose side and temple.
        eye = lm.eye_l.to(torch.float64)
        cand = skin & ~self.inside & (t[:, 0] > 0.18 * iod) & (t[:, 0] < eye[0] + 0.55 * iod)
        cand &= (t[:, 2] > eye[2] - 0.15 * iod)
        cand &= (t[:, 1] < eye[1] + 0.65 * iod) & (t[:, 1] > lm.mouth[1] - 0.1 * iod)
        cand &= ((t[:, :2] - eye[:2]).norm(dim=-1) > 0.42 * iod)  # not on the eye or the brow
        idx = torch.nonzero(cand).squeeze(1)
        if idx.numel() == 0:
            idx = torch.nonzero(skin & (t[:, 0] > 0)).squeeze(1)
        n_spots = 32
        pick = idx[torch.randint(idx.numel(), (n_spots,), generator=g)] if idx.numel() else idx
        self.spot_centres = (t[pick] + 0.004 * iod * torch.randn(pick.numel(), 3, generator=g,
                                                                 dtype=torch.float64)).float()
        sigma = 0.016 * iod * (0.6 + 0.8 * torch.rand(pick.numel(), generator=g, dtype=torch.float64))
        strength = 0.35 + 0.35 * torch.rand(pick.numel(), generator=g, dtype=torch.float64)
        self.spot_is_mole = torch.zeros(pick.numel(), dtype=torch.bool)
        self.spot_is_mole[:2] = True
        sigma[:2] = 0.030 * iod
        strength[:2] = 0.85
        self.spot_sigma, self.spot_strength = sigma.float(), strength.float()

    def _scatter_freckles(self, skin: Tensor, g: torch.Generator) -> DotField:
        """Freckle dots on the rest surface of the skin triangles, area-uniform then thinned by a density that is
        higher on the front of the face and on the subject's left, and patchy (a 2 cm noise)."""
        lm, iod = self.landmarks, self.landmarks.iod
        t = self.model.template.float()
        faces = self.model.faces[skin[self.model.faces].all(1)]
        if faces.shape[0] == 0:
            return DotField(torch.zeros(0, 3), torch.zeros(0), torch.zeros(0))
        tri = t[faces]
        area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
        count = int(min(float(area.sum()) / FRECKLE_SPACING**2, 50_000))
        pick = torch.multinomial(area.double(), count, replacement=True, generator=g) if count else faces[:0, 0]
        a, b = torch.rand(count, 1, generator=g), torch.rand(count, 1, generator=g)
        flip = (a + b) > 1
        a, b = torch.where(flip, 1 - a, a), torch.where(flip, 1 - b, b)
        c = tri[pick, 0] + a * (tri[pick, 1] - tri[pick, 0]) + b * (tri[pick, 2] - tri[pick, 0])
        front = _smoothstep(float(lm.eye_l[2]) - 1.2 * iod, float(lm.eye_l[2]) - 0.2 * iod, c[:, 2])
        density = 0.2 + 0.4 * front + self.freckle_density(c) + 0.3 * torch.tanh(c[:, 0] / (0.4 * iod))
        keep = torch.rand(count, generator=g) < density.clamp(0.0, 1.0)
        c = c[keep]
        n = c.shape[0]
        sigma = FRECKLE_SIGMA[0] + (FRECKLE_SIGMA[1] - FRECKLE_SIGMA[0]) * torch.rand(n, generator=g)
        strength = 0.4 + 0.4 * torch.rand(n, generator=g)
        return DotField(c, sigma, strength)

    def vertex_attributes(self) -> Tensor:
        """[V, 7] per-vertex attributes to interpolate: rest position, eyeball / teeth / tongue / mouth-interior
        weights."""
        m = self.model
        w = torch.zeros(m.num_vertices, 4)
        for k, keys in enumerate((("eyeball",), ("teeth", "tooth"), ("tongue",))):
            idx = _group(m, *keys)
            if idx.numel():
                w[idx, k] = 1.0
        w[self.inside, 3] = 1.0
        return torch.cat([m.template.float(), w], dim=1)

    def __call__(self, attrs: Tensor, footprint: Tensor | float = 0.0) -> Tensor:
        """Albedo RGB [N, 3] (float32, in [0, 1]) at N surface points given by interpolated attributes [N, 7]."""
        p = attrs[:, :3].float()
        n = p.shape[0]
        fp = (footprint.float() if torch.is_tensor(footprint) and footprint.dim() == 1
              else torch.full((n,), float(footprint)))
        w = attrs[:, 3:7].float().clamp(0.0, 1.0)
        out = torch.zeros(n, 3)
        skin_w = (1.0 - w[:, :3].sum(-1)).clamp_min(0.0)
        sel = skin_w > 0
        if bool(sel.any()):
            ps, fs = p[sel], fp[sel]
            col = self._skin(ps, fs)
            col = self._lips(ps, fs, col)
            col = self._brows(ps, fs, col)
            col = self._spots(ps, fs, col)
            inside = w[sel, 3:4]
            col = col * (1.0 - inside) + _rgb(MOUTH_INSIDE) * inside
            out[sel] = skin_w[sel, None] * col
        for k, layer in enumerate((self._eyes, self._teeth, self._tongue)):
            sel = w[:, k] > 0
            if bool(sel.any()):
                out[sel] += w[sel, k:k + 1] * layer(p[sel], fp[sel])
        return out.clamp(0.0, 1.0)

    # ------------------------------------------------------------------------------------------------------ layers
    def _skin(self, p: Tensor, fp: Tensor) -> Tensor:
        lm, iod = self.landmarks, self.landmarks.iod
        red = self.red(p)
        for c in (lm.eye_l, lm.eye_r):
            cheek = c + torch.tensor([0.12 * iod * float(torch.sign(c[0])), -0.62 * iod, 0.1 * iod])
            red = red + 0.09 * torch.exp(-((p - cheek) ** 2).sum(-1) / (2 * (0.28 * iod) ** 2))
        nose = torch.tensor([0.0, float(lm.eye_l[1]) - 0.55 * iod, float(lm.mouth[2]) + 0.1 * iod])
        red = red + 0.07 * torch.exp(-((p - nose) ** 2).sum(-1) / (2 * (0.18 * iod) ** 2))
        base = _rgb(SKIN) * (1.0 + self.tone(p)[:, None]) + red[:, None] * torch.tensor([0.06, -0.05, -0.04])
        # Mottling at 1-8 mm (luminance, a little chroma), then pores: dark dots where the 0.7 mm noise peaks.
        base = base * (1.0 + self.mottle(p, fp)[:, None]) + self.chroma(p, fp)[:, None] * torch.tensor(
            [0.04, -0.02, -0.03])
        pores = _smoothstep(0.8, 1.6, self.pores(p, fp))
        base = base * (1.0 - 0.25 * pores[:, None])
        # Freckles: 1-2.5 mm round brown dots scattered on the skin, denser on the face and on the subject's left.
        dots = self.freckles(p, fp).clamp(0.0, 0.85)
        return base * (1.0 - dots[:, None]) + (_rgb(FRECKLE) * base / _rgb(SKIN)) * dots[:, None]

    def _lips(self, p: Tensor, fp: Tensor, col: Tensor) -> Tensor:
        lm, iod = self.landmarks, self.landmarks.iod
        m = lm.mouth
        dx, dy, dz = p[:, 0] - m[0], p[:, 1] - m[1], p[:, 2] - m[2]
        hw = 0.40 * iod
        sel = (dx.abs() < hw) & (dy.abs() < 0.3 * iod) & (dz > -0.4 * iod)
        if not bool(sel.any()):
            return col
        dx, dy, dz = dx[sel], dy[sel], dz[sel]
        u = dx / hw
        profile = (1.0 - u * u).clamp_min(0.0).sqrt()
        up, down = 0.15 * iod * profile + 1e-5, 0.17 * iod * profile + 1e-5
        up = up * (1.0 - 0.18 * torch.exp(-(dx / (0.06 * iod)) ** 2))  # Cupid's bow
        r = torch.where(dy > 0, dy / up, -dy / down)
        lip = (1.0 - _smoothstep(0.8, 1.2, r)) * _smoothstep(-0.35 * iod, -0.2 * iod, dz)
        lips = _rgb(LIPS) * (1.0 + self.lip_lines(p[sel], fp[sel])[:, None])
        out = col.clone()
        out[sel] = col[sel] * (1.0 - lip[:, None]) + lips * lip[:, None]
        return out

    def _brows(self, p: Tensor, fp: Tensor, col: Tensor) -> Tensor:
        lm, iod = self.landmarks, self.landmarks.iod
        density = torch.zeros(p.shape[0])
        for e in (lm.eye_l, lm.eye_r):
            side = 1.0 if float(e[0]) > 0 else -1.0
            cx = float(e[0]) + side * 0.06 * iod
            hw = 0.40 * iod
            u = side * (p[:, 0] - cx) / hw  # -1 at the inner end, +1 at the outer end
            yc = float(e[1]) + 0.34 * iod + 0.07 * iod * (1.0 - (u - 0.15) ** 2)
            half = 0.075 * iod * (1.1 - 0.35 * u).clamp_min(0.3)
            v = (p[:, 1] - yc) / half
            band = (1.0 - _smoothstep(0.6, 1.25, v.abs())) * (1.0 - _smoothstep(0.85, 1.1, u.abs()))
            band = band * _smoothstep(float(e[2]) - 0.1 * iod, float(e[2]) + 0.05 * iod, p[:, 2])
            density = torch.maximum(density, band)
        sel = density > 0
        if not bool(sel.any()):
            return col
        # Hair strokes: noise stretched along the (mostly lateral) hair direction, and patchiness.
        ps, fs = p[sel], fp[sel]
        d = (density[sel] * (0.8 + self.hair(ps, fs) + self.brow_patch(ps))).clamp(0.0, 0.95)[:, None]
        out = col.clone()
        out[sel] = col[sel] * (1.0 - d) + _rgb(BROW) * d
        return out

    def _spots(self, p: Tensor, fp: Tensor, col: Tensor) -> Tensor:
        if self.spot_centres.numel() == 0:
            return col
        reach = 4.0 * float(self.spot_sigma.max()) + 2.0 * PREFILTER * fp  # [N]
        lo, hi = self.spot_centres.min(0).values, self.spot_centres.max(0).values
        sel = ((p > lo - reach[:, None]) & (p < hi + reach[:, None])).all(-1)
        if not bool(sel.any()):
            return col
        ps, fs, c = p[sel], fp[sel], col[sel]
        d2 = ((ps[:, None, :] - self.spot_centres[None]) ** 2).sum(-1)  # [n, S]
        sig2 = self.spot_sigma[None] ** 2
        eff2 = sig2 + (PREFILTER * fs[:, None]) ** 2  # prefiltered by the pixel (energy preserving)
        a = self.spot_strength[None] * (sig2 / eff2) * torch.exp(-d2 / (2 * eff2))
        freckle = (a * (~self.spot_is_mole)[None]).sum(-1).clamp(0.0, 0.9)[:, None]
        mole = (a * self.spot_is_mole[None]).sum(-1).clamp(0.0, 0.95)[:, None]
        c = c * (1.0 - freckle) + _rgb(FRECKLE) * (c / _rgb(SKIN)) * freckle
        out = col.clone()
        out[sel] = c * (1.0 - mole) + _rgb(MOLE) * mole
        return out

    def _eyes(self, p: Tensor, fp: Tensor) -> Tensor:
        lm = self.landmarks
        centre = torch.where(p[:, :1] > (lm.eye_l[0] + lm.eye_r[0]) / 2, lm.eye_l, lm.eye_r)
        d = torch.nn.functional.normalize(p - centre, dim=-1)
        theta = torch.acos(d[:, 2].clamp(-1.0, 1.0))  # angle from the eye's rest forward axis (+z)
        phi = torch.atan2(d[:, 1], d[:, 0])
        iris_r, pupil_r = 0.50, 0.17
        r = lm.eye_radius
        # Radial fibres: noise on (arc length around the axis, arc length from it), long along the radius.
        polar = torch.stack([phi * r * 0.48, theta * r, torch.zeros_like(phi)], -1)
        iris = _rgb(self.iris) * (1.0 + self.iris_fibres(polar, fp)[:, None])
        iris = iris * (1.0 - 0.5 * _smoothstep(iris_r - 0.12, iris_r, theta))[:, None]  # the limbal ring
        sclera = _rgb(SCLERA) * (1.0 + self.veins(p, fp)[:, None])
        sclera = sclera * (1.0 - 0.12 * _smoothstep(0.9, 1.6, theta))[:, None]
        aa = (0.5 * fp / r).clamp(0.02, 0.2)  # edge softness in radians: about a pixel
        in_iris = (1.0 - _smoothstep(0.0, 1.0, (theta - iris_r) / aa + 0.5))[:, None]
        in_pupil = (1.0 - _smoothstep(0.0, 1.0, (theta - pupil_r) / aa + 0.5))[:, None]
        col = sclera * (1.0 - in_iris) + iris * in_iris
        return col * (1.0 - in_pupil) + _rgb(PUPIL) * in_pupil

    def _teeth(self, p: Tensor, fp: Tensor) -> Tensor:
        return _rgb(TEETH) * (1.0 + self.teeth_var(p, fp)[:, None])

    def _tongue(self, p: Tensor, fp: Tensor) -> Tensor:
        return _rgb(TONGUE) * (1.0 + self.tongue_bumps(p, fp)[:, None])


def lambert(albedo: Tensor, normals: Tensor, view: Tensor | None = None,
            light: tuple[float, float, float] = LIGHT, ambient: float = AMBIENT, diffuse: float = DIFFUSE) -> Tensor:
    """Shaded colour [N, 3] = albedo (ambient + diffuse max(0, n . l)) with one directional light (world frame).

    ``normals`` [N, 3] need not be unit; with ``view`` [N, 3] (surface -> camera directions) a normal facing away
    from the camera is flipped first (two-sided lighting: the mouth interior and back faces seen through it)."""
    n = torch.nn.functional.normalize(normals.to(torch.float64), dim=-1)
    if view is not None:
        flip = (n * view.to(torch.float64)).sum(-1, keepdim=True) < 0
        n = torch.where(flip, -n, n)
    ldir = torch.nn.functional.normalize(torch.tensor(light, dtype=torch.float64, device=n.device), dim=0)
    shade = ambient + diffuse * (n @ ldir).clamp_min(0.0)
    return (albedo.to(torch.float64) * shade[:, None]).clamp(0.0, 1.0).to(albedo.dtype)

