// Orchestration of the training forward and the backward of the posed-Gaussian rasterizer (see backward.hpp).
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <stdexcept>

#include "backward.hpp"

namespace bs {

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

constexpr int kChunk = 512;  // Gaussians per parallel work item

// goff[n] = first pair slot of Gaussian n of one frame (its tiles, row-major), goff[N] = the frame's pairs.
void pair_offsets(const Splat* s, int n, uint32_t* goff) {
    uint64_t run = 0;
    for (int i = 0; i < n; ++i) {
        goff[i] = uint32_t(run);
        if (s[i].x0 < s[i].x1) {
            const TileRect r = tile_rect(s[i]);
            run += uint64_t(r.x1 - r.x0 + 1) * uint64_t(r.y1 - r.y0 + 1);
        }
    }
    if (run >= (uint64_t(1) << 32)) throw std::length_error("more than 2^32 (Gaussian, tile) pairs in one frame");
    goff[n] = uint32_t(run);
}

}  // namespace

const BackwardKernels& backward_kernels_for(const Kernels& k) {
#ifdef BS_HAVE_AVX512
    if (std::strcmp(k.name, "avx512") == 0) return avx512::backward_kernels();
#endif
#ifdef BS_HAVE_AVX2
    if (std::strcmp(k.name, "avx2") == 0) return avx2::backward_kernels();
#endif
    return scalar::backward_kernels();
}

size_t RasterContext::pairs() const {
    size_t n = 0;
    for (const auto& f : frames) n += f.ids.size();
    return n;
}

size_t RasterContext::nbytes() const {
    size_t n = splats.size() * sizeof(Splat) + cams.size() * sizeof(Cam);
    for (const auto& f : frames)
        n += (f.ids.size() + f.tile_offsets.size() + f.last.size()) * sizeof(uint32_t) + f.T.size() * sizeof(float);
    return n;
}

Timings rasterize_train(const PosedView& pv, const Cam* cams, int B, const float* bg, float* rgb, float* alpha,
                        float* depth, const Kernels& k, int threads, RasterContext& ctx) {
    Timings tm;
    const BackwardKernels& kb = backward_kernels_for(k);
    const int N = pv.N, W = cams[0].width, H = cams[0].height;
    ctx.B = B, ctx.N = N, ctx.width = W, ctx.height = H;
    ctx.cams.assign(cams, cams + B);
    ctx.k = &k, ctx.kb = &kb;
    ctx.splats.resize(size_t(B) * N);
    ctx.frames.resize(B);
    Splat* splats = ctx.splats.data();
    const int chunks = (N + kChunk - 1) / kChunk;
    auto t0 = Clock::now();
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int job = 0; job < B * chunks; ++job) {
        const int b = job / chunks, c = job % chunks;
        const int n0 = c * kChunk, n1 = std::min(N, n0 + kChunk);
        Splat* out = splats + size_t(b) * N;
        k.project_posed(pv, b, cams[b], out, n0, n1);
        for (int n = n0; n < n1; ++n) out[n].t.id = uint32_t(n);
    }
    tm.lbs_ms = ms_since(t0);

    t0 = Clock::now();
    static thread_local std::vector<FrameBins> bins_tls;  // the caller's; worker threads use it by reference
    std::vector<FrameBins>& bins = bins_tls;
    if (int(bins.size()) < B) bins.resize(B);
    const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile, tiles = tiles_x * tiles_y;
    for (int b = 0; b < B; ++b) {
        bin_frame(splats + size_t(b) * N, N, tiles_x, tiles, bins[b], threads);
        TrainFrame& f = ctx.frames[b];
        f.T.resize(size_t(W) * H);
        f.last.resize(size_t(W) * H);
    }
    tm.bin_ms = ms_since(t0);
    const int jobs = B * tiles;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 4)
    for (int job = 0; job < jobs; ++job) {
        const int b = job / tiles, t = job % tiles;
        const FrameBins& fb = bins[b];
        TrainFrame& f = ctx.frames[b];
        const size_t pix = size_t(b) * W * H;
        const uint32_t o0 = fb.tile_offsets[t];
        kb.raster_tile_train(fb.sorted.data(), fb.binned.data() + o0, int(fb.tile_offsets[t + 1] - o0),
                             t % tiles_x, t / tiles_x, cams[b], bg + 3 * b, rgb + pix * 3, alpha + pix, depth + pix,
                             f.T.data(), f.last.data());
    }
    // The Gaussian index of each tile-list entry.
    for (int b = 0; b < B; ++b) {
        const FrameBins& fb = bins[b];
        TrainFrame& f = ctx.frames[b];
        f.tile_offsets = fb.tile_offsets;
        f.ids.resize(fb.binned.size());
        const int64_t m = int64_t(fb.binned.size());
        const uint32_t* pos = fb.binned.data();
        const TileSplat* sorted = fb.sorted.data();
        uint32_t* dst = f.ids.data();
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int64_t i = 0; i < m; ++i) dst[i] = sorted[pos[i]].id;
    }
    tm.raster_ms = ms_since(t0);
    return tm;
}

BackwardTimings rasterize_backward(const RasterContext& ctx, const PosedView& pv, const float* bg,
                                   const float* grad_rgb, const float* grad_alpha, const PosedGrads& g, int threads) {
    BackwardTimings tm;
    const int B = ctx.B, N = ctx.N, W = ctx.width, H = ctx.height;
    const BackwardKernels& kb = *ctx.kb;
    const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile, tiles = tiles_x * tiles_y;
    auto t0 = Clock::now();
    // Pair slots: Gaussian-major (each Gaussian's tiles in row-major order), frames one after the other.
    static thread_local std::vector<uint32_t> goff_tls;
    static thread_local std::vector<float> moments_tls;
    std::vector<uint32_t>& goff = goff_tls;
    std::vector<float>& moments = moments_tls;
    goff.resize(size_t(B) * (N + 1));
    std::vector<size_t> frame_pairs(B + 1, 0);
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int b = 0; b < B; ++b) pair_offsets(ctx.splats.data() + size_t(b) * N, N, goff.data() + size_t(b) * (N + 1));
    for (int b = 0; b < B; ++b) {
        const uint32_t pairs = goff[size_t(b) * (N + 1) + N];
        if (pairs != ctx.frames[b].ids.size()) throw std::logic_error("backward: pair count differs from the bins");
        frame_pairs[b + 1] = frame_pairs[b] + pairs;
    }
    moments.resize(frame_pairs[B] * kMoments);
    const int jobs = B * tiles;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 2)
    for (int job = 0; job < jobs; ++job) {
        const int b = job / tiles, t = job % tiles;
        const TrainFrame& f = ctx.frames[b];
        const size_t pix = size_t(b) * W * H;
        const uint32_t off = f.tile_offsets[t];
        kb.backward_tile(ctx.splats.data() + size_t(b) * N, f.ids.data() + off, int(f.tile_offsets[t + 1] - off),
                         t % tiles_x, t / tiles_x, ctx.cams[b], f.T.data(), f.last.data(), grad_rgb + pix * 3,
                         grad_alpha + pix, bg + 3 * b, goff.data() + size_t(b) * (N + 1),
                         moments.data() + frame_pairs[b] * kMoments);
    }
    tm.raster_ms = ms_since(t0);
    t0 = Clock::now();
    const int chunks = (N + kChunk - 1) / kChunk;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int job = 0; job < B * chunks; ++job) {
        const int b = job / chunks, c = job % chunks;
        const int n0 = c * kChunk, n1 = std::min(N, n0 + kChunk);
        kb.project_backward(pv, b, ctx.cams[b], ctx.splats.data() + size_t(b) * N, goff.data() + size_t(b) * (N + 1),
                            moments.data() + frame_pairs[b] * kMoments, g, n0, n1);
    }
    tm.project_ms = ms_since(t0);
    return tm;
}

}  // namespace bs
