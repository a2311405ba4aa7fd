// The native renderer's entry points (used by module.cpp).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common.hpp"

namespace bs {

struct Timings {
    double blend_ms = 0.0, lbs_ms = 0.0, raster_ms = 0.0;
    double bin_ms = 0.0;  // part of raster_ms: depth sort and tile binning
};

// Tile rectangle of a visible splat (inclusive): the tiles bin_frame puts it in.
struct TileRect {
    uint16_t x0, x1, y0, y1;
};

inline TileRect tile_rect(const Splat& s) {
    return {uint16_t(int(s.x0) / kTile), uint16_t((int(s.x1) - 1) / kTile), uint16_t(int(s.y0) / kTile),
            uint16_t((int(s.y1) - 1) / kTile)};
}

// One frame's depth order and tile bins (bin_frame); the vectors are reused from call to call.
struct FrameBins {
    std::vector<uint32_t> order, tmp, keys, tmp_keys, tile_offsets;
    std::vector<uint32_t> merged;  // the depth order merged from two sorted halves (several threads)
    std::vector<uint32_t> counts;  // [threads, tiles]
    std::vector<uint32_t> hist;    // [2, 2048]
    std::vector<TileSplat> sorted;  // the visible splats in depth order
    std::vector<TileRect> rects;    // their tile rectangles
    std::vector<uint32_t> binned;   // per tile, positions in sorted
};

// Visible splats (x0 < x1) of one frame [n], depth-sorted (ties by index) into fb.sorted; tile t's splats are
// fb.sorted[fb.binned[j]] for j in [tile_offsets[t], tile_offsets[t + 1]), in depth order.
void bin_frame(const Splat* s, int n, int tiles_x, int tiles, FrameBins& fb, int threads);

// SIMD paths this build can run on this CPU, slowest first ("scalar", then "avx2", "avx512").
std::vector<std::string> available_isas();
// "auto" picks the fastest; an unavailable name throws std::invalid_argument listing the available ones.
const Kernels& select_kernels(const std::string& isa);

// The outputs of B frames: rgb [B, H, W, 3], alpha and depth [B, H, W], 8-bit RGBA [B, H, W, 4]; any may be null.
struct FrameOut {
    float* rgb = nullptr;
    float* alpha = nullptr;
    float* depth = nullptr;
    uint8_t* rgba8 = nullptr;
};

// B frames of one avatar: psi [B, K], rot [B, J, 3, 3], eyelids [B, 2], cams [B], bg [B, 3]; the compositing
// schedule of flags (RasterFlags).
Timings render_fused(const AvatarView& av, const float* psi, const float* rot, const float* eyelids, const Cam* cams,
                     int B, const float* bg, const FrameOut& out, const Kernels& k, int threads,
                     unsigned flags = kRasterDefault);

// B frames of already posed Gaussians (colours evaluated).
Timings render_posed(const PosedView& pv, const Cam* cams, int B, const float* bg, const FrameOut& out,
                     const Kernels& k, int threads, unsigned flags = kRasterDefault);

}  // namespace bs
