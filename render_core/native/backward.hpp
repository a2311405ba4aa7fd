// The backward pass of the posed-Gaussian rasterizer (docs/method.md section 9): a training forward that also keeps
// what the backward needs, and the backward itself (raster_backward.cpp orchestrates; backward.inl holds the
// kernels, compiled once per instruction set like kernels.inl).
//
// Gradient flow: per pixel, compositing is walked back to front from the last contributing splat (the forward
// stores each pixel's final transmittance and that splat's position in its tile list); each (Gaussian, tile) pair
// gets 9 moments of the per-pixel gradients (see kMoments); each Gaussian then sums its pairs' moments in tile
// order and runs the projection backward (conic, opacity, EWA covariance, clamped Jacobian, quaternion, scale,
// mean). Every sum has a fixed order, so the gradients are bitwise the same for any thread count.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "pipeline.hpp"

namespace bs {

// Moments per (Gaussian, tile) pair, summed over the tile's pixels where the Gaussian contributes, with
// v = a dL/da (zero where alpha is clamped at 0.999), dx = mean_x - pixel_x, dy = mean_y - pixel_y (pixel centres)
// and w = a T (the compositing weight):
//   sum v, sum v dx, sum v dx^2, sum v dy, sum v dx dy, sum v dy^2, sum w dL/dr, sum w dL/dg, sum w dL/db.
constexpr int kMoments = 9;

// Per-Gaussian gradients the backward writes ([B, N, ...] float32, fully overwritten).
struct PosedGrads {
    float* means;      // [B, N, 3]
    float* quats;      // [B, N, 4]
    float* scales;     // [B, N, 3]
    float* opacities;  // [B, N]
    float* colors;     // [B, N, 3]
};

// What one frame's training forward keeps for the backward.
struct TrainFrame {
    std::vector<uint32_t> ids;           // [pairs] Gaussian of each tile-list entry, tile by tile, in depth order
    std::vector<uint32_t> tile_offsets;  // [tiles + 1] tile t's entries are ids[tile_offsets[t], tile_offsets[t+1])
    std::vector<float> T;                // [H * W] final transmittance
    std::vector<uint32_t> last;          // [H * W] 1 + tile-list position of the last contributor (0: none)
};

struct BackwardKernels;

// The state a training forward leaves for its backward (owned by Python through the bindings).
struct RasterContext {
    int B = 0, N = 0, width = 0, height = 0;
    std::vector<Cam> cams;
    std::vector<Splat> splats;  // [B, N] projected splats (TileSplat::id = index in the frame)
    std::vector<TrainFrame> frames;
    const Kernels* k = nullptr;
    const BackwardKernels* kb = nullptr;
    // Bytes held between forward and backward.
    size_t nbytes() const;
    size_t pairs() const;  // (Gaussian, tile) pairs over all frames
};

struct BackwardKernels {
    const char* name;
    // As Kernels::raster_tile (the eager 8 x 2 schedule), and also each pixel's final transmittance T and
    // last-contributor count (frame arrays [H * W], like alpha).
    void (*raster_tile_train)(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty, const Cam& cam,
                              const float* background, float* rgb, float* alpha, float* depth, float* T,
                              uint32_t* last);
    // Backward of one tile's compositing: moments of every (Gaussian, tile) pair of the tile, written at
    // moments + kMoments * slot, slot = goff[id] + the tile's rank among the Gaussian's tiles (row-major).
    // Frame arrays: splats [N], T, last, grad_alpha [H * W], grad_rgb [H * W * 3]; background [3].
    void (*backward_tile)(const Splat* splats, const uint32_t* ids, int count, int tx, int ty, const Cam& cam,
                          const float* T, const uint32_t* last, const float* grad_rgb, const float* grad_alpha,
                          const float* background, const uint32_t* goff, float* moments);
    // Projection backward of Gaussians [n0, n1) of frame b: sums each one's pair moments, writes its gradients.
    void (*project_backward)(const PosedView& pv, int b, const Cam& cam, const Splat* splats, const uint32_t* goff,
                             const float* moments, const PosedGrads& g, int n0, int n1);
};

namespace scalar { const BackwardKernels& backward_kernels(); }
namespace avx2 { const BackwardKernels& backward_kernels(); }
namespace avx512 { const BackwardKernels& backward_kernels(); }

// The backward kernels of the instruction set named like Kernels::name.
const BackwardKernels& backward_kernels_for(const Kernels& k);

struct BackwardTimings {
    double raster_ms = 0.0;   // compositing backward (tiles)
    double project_ms = 0.0;  // pair reduction + projection backward
};

// Forward of B frames of posed Gaussians (as render_posed) that fills ctx for rasterize_backward.
Timings rasterize_train(const PosedView& pv, const Cam* cams, int B, const float* bg, float* rgb, float* alpha,
                        float* depth, const Kernels& k, int threads, RasterContext& ctx);

// Gradients of a loss given dL/drgb [B, H, W, 3] and dL/dalpha [B, H, W] (bg: [B, 3], as in the forward).
// pv: the forward's inputs (colors unused). The background's gradient is sum_pixels T dL/drgb (computed by the
// caller from ctx's T).
BackwardTimings rasterize_backward(const RasterContext& ctx, const PosedView& pv, const float* bg,
                                   const float* grad_rgb, const float* grad_alpha, const PosedGrads& g, int threads);

}  // namespace bs
