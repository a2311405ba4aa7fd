// Data shared by the pipeline (pipeline.cpp) and the per-instruction-set kernels (kernels.inl).
#pragma once

#include <cstdint>

namespace bs {

constexpr int kTile = 16;
constexpr float kNear = 0.01f;
constexpr float kEps2d = 0.3f;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.999f;
constexpr float kTStop = 1e-4f;
// The 8-bit stop (kEightBitStop): a pixel whose transmittance falls below this after a splat is composited stops
// (as well as where the exact rule stops it); what lies behind could change its colour by a quarter of a level.
constexpr float kTStop8 = 1.0f / 1020.0f;
static_assert(kTStop < kTStop8, "the 8-bit stop lies above the exact one: it covers it (composite_tile)");
constexpr int kMaxBatch = 64;  // frames blended together per pass (larger batches are split)

// A packed avatar (render_core/packed.py: the layout of a schema-2 bundle; the arrays belong to Python).
// base rows (Dp = 16 + ceil16(3C) floats): position 3, quaternion 4 (wxyz), log-scale 3, opacity logit 1, 5 unused,
// then SH 3C (coefficient-major, channel-minor) and unused to Dp. The blendshapes are two CSR tables over the face
// Gaussians: geometry pairs of 11 values (added to base columns 0..15) and colour pairs of 3C values (added to
// columns 16..Dp). Pair rows are packed at stride len and each array ends with ceil16(len) - len spare values, so
// 16-value loads of the last row stay inside it; lanes past len land in unused columns.
// int8 values are scaled (packed.py): value[d] = q[d] * scale[k][d], the geometry's columns 0..2 (q[d] + r[j][d] /
// 256) * scale[k][d] with r the position residuals (3 per pair, 13 spare bytes at the end); scale rows are
// ceil16(len) floats, zero past len, so the lanes past len get no weight.
struct PairsView {
    const int32_t* row_ptr = nullptr;  // [n_face + 1]
    const uint16_t* col = nullptr;     // [nnz] blendshape index of each stored pair
    const void* vals = nullptr;        // [nnz * len + ceil16(len) - len]
    int len = 0;
    const float* scale = nullptr;     // int8: [K, ceil16(len)]
    const int8_t* residual = nullptr;  // int8 geometry: [nnz * 3 + 13], the positions' second byte
};

constexpr int kPositionColumns = 3;     // the geometry columns with a residual byte
constexpr float kResidualStep = 1.0f / 256.0f;  // a residual's unit, in steps of its value

// Storage of the pair values (pc: fp32 with kF32, fp16 otherwise).
enum class Storage : uint8_t { kF32, kF16, kI8 };

struct AvatarView {
    int n_total = 0;  // face + mouth Gaussians
    int n_face = 0;
    int K = 0, J = 0, C = 0, Dp = 0;
    int P = 0, Ppad = 0;  // pose-corrective features 9 (J - 1), padded to 16
    Storage storage = Storage::kF32;  // pair values fp32, fp16 (uint16 bits) or int8 (and scales)
    const float* base = nullptr;        // [n_total, Dp]
    PairsView geometry, color;
    const void* pc = nullptr;           // [n_face, 3, Ppad] pose correctives (fp32 or fp16 bits), or null
    const float* eyelid = nullptr;      // [n_face, 2, 3] eyelid offsets, or null
    const float* lbs = nullptr;         // [J, n_total] skinning weights (mouth: one-hot on its joint)
    const float* joints = nullptr;      // [J, 3] rest positions
    const int32_t* parents = nullptr;   // [J]
};

struct Cam {
    float fx, fy, cx, cy;
    float R[9];
    float t[3];
    float centre[3];
    int width, height;
    bool antialiased;
};

// A projected Gaussian as the compositing loop reads it (48 bytes). The conic and levels are in base 2:
// q = sigma log2(e) = ha dx^2 + cb dx dy + hc dy^2, alpha = min(0.999, 2^(log2_opacity - q)).
struct TileSplat {
    float mx, my;                // pixel-space centre
    float ha, cb, hc;            // conic times log2(e), diagonal terms halved
    float log2_opacity, depth;   // compositing opacity (antialiasing compensation included), camera z
    float r, g, b;               // colour
    float level;                 // log2(255 opacity): eligible only where q <= level
    uint32_t id;                 // Gaussian index in its frame (set where the backward needs it, else 0)
};
static_assert(sizeof(TileSplat) == 48, "TileSplat is 48 bytes");

// The projection's output: the compositing record and the pixels whose centres can pass eligibility
// (half-open; empty when culled), which decide the tiles it is binned into. One cache line, aligned to one: the
// binning reads the splats in depth order, at random, and a record that straddles two lines costs two misses
// (with 16-byte aligned vectors every record straddled, its x0..y1 on the second, unprefetched line).
struct alignas(64) Splat {
    TileSplat t;
    float x0, x1, y0, y1;
};
static_assert(sizeof(Splat) == 64 && alignof(Splat) == 64, "Splat is one cache line");

// Posed Gaussians (world space) for the raster-only entry point, array-of-structs per batch.
struct PosedView {
    const float* means;      // [B, N, 3]
    const float* quats;      // [B, N, 4] wxyz
    const float* scales;     // [B, N, 3]
    const float* opacities;  // [B, N]
    const float* colors;     // [B, N, 3]
    int N;
};

// Where one tile's pixels go (frame arrays, the tile's pixels written, the rest untouched): float RGB [H, W, 3],
// alpha and depth [H, W] and 8-bit RGBA [H, W, 4] (as to_rgba8 rounds the floats); any may be null. Training's
// forward also writes the final transmittance T and the last contributor (1-based; 0: none) per pixel.
struct TileOut {
    float* rgb = nullptr;
    float* alpha = nullptr;
    float* depth = nullptr;
    uint8_t* rgba8 = nullptr;
    float* T = nullptr;
    uint32_t* last = nullptr;
};

// Compositing schedule switches (each changes how the work is done, never a pixel: the images are bit-identical).
enum RasterFlags : unsigned {
    kLazyTiles = 1u,     // gather a tile's splats and their row spans a chunk at a time; stop when every pixel stopped
    kSquareBlocks = 2u,  // blocks of 4 x 4 pixels (16 lanes; 4 x 2 with 8) instead of 8 x 2 (8 x 1)
    kRasterDefault = kLazyTiles | kSquareBlocks,
    // Not a schedule switch, a precision one: on 8-bit output alone (no float image asked for), each pixel also
    // stops once a composited splat takes its transmittance below kTStop8 (the exact rule goes on to kTStop): the
    // 8-bit values stay within a quarter of a level of the exact ones before rounding (colours in 0..1).
    kEightBitStop = 4u,
    kRasterKnown = kRasterDefault | kEightBitStop,
};

struct Kernels {
    const char* name;
    // Eq. 1 blend + pose correctives + eyelids of Gaussians [n0, n1) for B frames: the row of Gaussian n in
    // frame b goes to out + (b * out_stride + n - n0) * Dp.
    void (*blend)(const AvatarView& av, const float* psi, const float* pose_feat, const float* eyelids, int B,
                  float* out, int out_stride, int n0, int n1);
    // LBS, rotation, activation, SH colour and projection of one frame's blended Gaussians [n0, n1)
    // (blended points at the row of n0) into out[n0, n1).
    void (*deform_project)(const AvatarView& av, const float* blended, const float* A, const Cam& cam, Splat* out,
                           int n0, int n1);
    // Projection of already posed Gaussians [n0, n1) of one frame.
    void (*project_posed)(const PosedView& pv, int b, const Cam& cam, Splat* out, int n0, int n1);
    // Front-to-back compositing of one 16x16 tile from its count splats in depth order: sorted[pos[j]] (pos null:
    // sorted[j]), with the schedule of flags (RasterFlags).
    void (*raster_tile)(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty, const Cam& cam,
                        const float* background, const TileOut& out, unsigned flags);
};

namespace scalar { const Kernels& kernels(); }
namespace avx2 { const Kernels& kernels(); }
namespace avx512 { const Kernels& kernels(); }

}  // namespace bs
