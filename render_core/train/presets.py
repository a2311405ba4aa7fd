"""Training presets: ``tiny`` (minutes on a 2-core CPU) and ``paper`` (docs/method.md section 6)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from ..errors import OptionError


@dataclass(frozen=True)
class Preset:
    name: str
    iterations: int
    gaussians: int  # initial face Gaussians
    mouth: int  # mouth-interior Gaussians (two billboards)
    sh_degree: int = 3
    sh_every: int = 1000  # SH degree + 1 every this many iterations
    consistency: str = "all"
    # Learning rates (docs/method.md section 6). Neutral (also used for the mouth interior):
    lr_xyz: float = 1.6e-4
    lr_xyz_final: float = 1.6e-6
    xyz_decay_steps: int = 30_000
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 1.25e-4
    lr_opacity: float = 0.05
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    # Blendshape residuals dG_hat (the paper):
    lr_hat_xyz: float = 3.2e-7
    lr_hat_opacity: float = 5e-5
    lr_hat_scale: float = 5e-4
    lr_hat_rotation: float = 1e-4
    lr_hat_sh: float = 1.25e-3
    # Densification and pruning (:mod:`.densify`).
    densify: bool = True
    max_gaussians: int = 200_000
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    densify_grad: float = 1e-3
    prune_opacity: float = 0.005
    prune_big_after: int = 3000  # world-size (> 0.1 x extent) and screen-size pruning only after this iteration
    max_screen_radius: float = 20.0  # pixels (3DGS's max_screen_size)
    grid_resolution: int = 256  # lookup grid for children's and moved Gaussians' LBS weights and d (0: no grid,
    # children copy their parent's)
    # Pruning by contribution (:mod:`.prune`): at these iterations (none: off) the face Gaussians with the least
    # blending weight over ``prune_frames`` training frames go; ``prune_fraction`` of them in all (0: off).
    prune_at: tuple[int, ...] = ()
    prune_fraction: float = 0.0
    prune_frames: int = 24
    # the score (``train --prune-by``): "peak" (the largest weight in any one frame: held-out head PSNR 0.06-0.08 dB
    # above the sum's at 60% on data synth seeds 257 with training seeds 0 and 1), "contribution" (the summed
    # weight) or "efficiency" (that weight per pixel the Gaussian costs to render: :func:`.prune.footprints`)
    prune_by: str = "peak"
    # the mouth interior pruned too, by the same fraction, ranked among itself (False: never pruned, as before
    # 2026-12-04); its scores lie far below the face's, and pruning 60% of it cost nothing measurable
    prune_mouth: bool = True
    # Per-frame head poses refined with the avatar (:mod:`.poses`), from this iteration on: for tracked videos whose
    # poses are off by about a pixel (``blendsplat track``'s output; ``train --refine-poses``).
    refine_poses: bool = False
    # ... and their expression coefficients (under a prior), with the poses: a blink or smile the tracker missed in
    # one frame (``train --refine-expressions``)
    refine_expressions: bool = False
    # 200 (was 500): held-out head PSNR of `blendsplat track`'s output (data synth seed 257, tiny, 1500 iterations,
    # --refine-expressions) 26.88 -> 27.33 dB (100: 27.29); seed 311 27.10 -> 27.25
    refine_poses_from: int = 200
    # The corrections' learning rate at the end of the run, as a fraction of their first (an exponential decay from
    # refine_poses_from on; 1.0: constant, as before 2026-12-01). Adam moves a frame's correction by about its
    # learning rate at every step it takes, so a constant rate leaves each correction about one step off: trained
    # on the TRUE tracking of data synth seed 257 (tiny, 1500 iterations) with the corrections on, the held-out
    # head PSNR fell 29.45 -> 28.87 dB and the training frames' 36.9 -> 34.8 dB
    refine_lr_final: float = 0.05
    # Bookkeeping.
    checkpoint_every: int = 1000
    log_every: int = 10
    final_eval_frames: int = 8  # training frames re-rendered at the end (summary "final")
    init_opacity: float = 0.1
    threads: int = 0  # rasterizer threads (0: all)

    def with_(self, **overrides) -> Preset:
        return replace(self, **overrides)

    def with_gaussians(self, gaussians: int) -> Preset:
        """The preset scaled to ``gaussians`` initial face Gaussians (``train --gaussians``): mouth Gaussians at
        most a tenth of them, the densification cap scaled alike."""
        return replace(self, gaussians=gaussians, mouth=max(2, min(self.mouth, gaussians // 10)),
                       max_gaussians=max(gaussians, self.max_gaussians * gaussians // self.gaussians))

    def with_pruning(self, fraction: float, at: tuple[int, ...] | None = None) -> Preset:
        """Contribution pruning (``train --prune``): ``fraction`` (0 <= f < 1; 0: off) of the face Gaussians removed
        in all, at iterations ``at`` (default: one densification interval after densification ends and 40% of
        the way from there to the last iteration, so that the rest fine-tunes the survivors)."""
        fraction = float(fraction)
        if not 0.0 <= fraction < 1.0:
            raise OptionError(f"must be in [0, 1), got {fraction}", field="prune")
        if fraction == 0.0:
            return replace(self, prune_at=(), prune_fraction=0.0)
        if at is None:
            end = min(self.densify_until if self.densify else 0, self.iterations)
            at = (end + self.densify_every, end + 2 * (self.iterations - end) // 5)
        at = tuple(sorted({int(i) for i in at if 0 < int(i) < self.iterations}))
        if not at:
            raise OptionError(f"no pruning iteration falls inside the {self.iterations} iterations", field="prune")
        return replace(self, prune_at=at, prune_fraction=fraction)

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS: dict[str, Preset] = {
    # A few minutes on a 2-core CPU at 256 x 256: 20k Gaussians (densified up to 30k), the xyz decay over the run,
    # SH ramp every 300.
    "tiny": Preset(name="tiny", iterations=3000, gaussians=20_000, mouth=2_000, sh_every=300, xyz_decay_steps=3000,
                   densify_from=500, densify_until=2000, max_gaussians=30_000, checkpoint_every=500, log_every=10),
    # The paper's numbers: 40k iterations, 50k face Gaussians, 2 x 5k mouth Gaussians (reference code).
    "paper": Preset(name="paper", iterations=40_000, gaussians=50_000, mouth=10_000, sh_every=1000,
                    xyz_decay_steps=30_000, checkpoint_every=5000, log_every=50),
}


def get_preset(preset: str | Preset) -> Preset:
    if isinstance(preset, Preset):
        return preset
    if preset not in PRESETS:
        raise OptionError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}", field="preset")
    return PRESETS[preset]
