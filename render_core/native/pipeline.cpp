// Per-frame orchestration: joint transforms, the parallel stages (blend, deform + project, raster), and the
// depth sort and tile binning between them. Kernels come from the instruction set chosen at run time.
#include "pipeline.hpp"

#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <stdexcept>
#include <vector>

namespace bs {

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

bool cpu_has(const char* isa) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    if (std::strcmp(isa, "avx2") == 0)
        return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("f16c");
    if (std::strcmp(isa, "avx512") == 0) return __builtin_cpu_supports("avx512f");
#endif
    return std::strcmp(isa, "scalar") == 0;
}

// Skinning transforms A_j = A_parent [R_j | (I - R_j) J_j] (render_core.deform.joint_transforms), [J, 12].
void joint_transforms(const AvatarView& av, const float* rot, float* A) {
    for (int j = 0; j < av.J; ++j) {
        const float* r = rot + j * 9;
        const float* p = av.joints + j * 3;
        float local[12];
        for (int i = 0; i < 3; ++i) {
            for (int c = 0; c < 3; ++c) local[4 * i + c] = r[3 * i + c];
            local[4 * i + 3] = p[i] - (r[3 * i] * p[0] + r[3 * i + 1] * p[1] + r[3 * i + 2] * p[2]);
        }
        float* a = A + j * 12;
        const int parent = av.parents[j];
        if (parent < 0) {
            std::memcpy(a, local, sizeof(local));
            continue;
        }
        const float* pa = A + parent * 12;
        for (int i = 0; i < 3; ++i) {
            for (int c = 0; c < 4; ++c) {
                float s = c == 3 ? pa[4 * i + 3] : 0.0f;
                for (int k = 0; k < 3; ++k) s += pa[4 * i + k] * local[4 * k + c];
                a[4 * i + c] = s;
            }
        }
    }
}

// fb.order = indices of the visible splats sorted by depth, ties in index order: a stable LSD radix sort of 11
// bits a pass over the bits of the positive float depths (whose order is their bits' order) less the smallest:
// only as many passes as the frame's range of bits needs (two for a head, whose depths span a narrow range).
void sort_visible_by_depth(const Splat* s, int n, FrameBins& fb) {
    constexpr int kBuckets = 2048;
    fb.order.resize(n), fb.keys.resize(n), fb.tmp.resize(n), fb.tmp_keys.resize(n);
    int m = 0;
    uint32_t lo = UINT32_MAX, hi = 0;
    for (int i = 0; i < n; ++i) {
        if (!(s[i].x0 < s[i].x1)) continue;
        fb.order[m] = uint32_t(i);
        uint32_t key;
        std::memcpy(&key, &s[i].t.depth, 4);
        fb.keys[m] = key, lo = std::min(lo, key), hi = std::max(hi, key);
        ++m;
    }
    for (int j = 0; j < m; ++j) fb.keys[j] -= lo;
    const uint32_t range = m > 0 ? hi - lo : 0;
    fb.hist.resize(kBuckets);
    uint32_t* h = fb.hist.data();
    for (int sh = 0; sh < 32 && (sh == 0 || (range >> sh) != 0); sh += 11) {
        std::fill(h, h + kBuckets, 0u);
        const uint32_t* idx = fb.order.data();
        const uint32_t* key = fb.keys.data();
        for (int j = 0; j < m; ++j) ++h[(key[j] >> sh) & (kBuckets - 1)];
        uint32_t run = 0;
        for (int b = 0; b < kBuckets; ++b) {
            const uint32_t c = h[b];
            h[b] = run;
            run += c;
        }
        uint32_t* out_idx = fb.tmp.data();
        uint32_t* out_key = fb.tmp_keys.data();
        for (int j = 0; j < m; ++j) {
            const uint32_t dst = h[(key[j] >> sh) & (kBuckets - 1)]++;
            out_idx[dst] = idx[j], out_key[dst] = key[j];
        }
        fb.order.swap(fb.tmp);
        fb.keys.swap(fb.tmp_keys);
    }
    fb.order.resize(m);
}

}  // namespace

// Visible splats of one frame in depth order (ties by index) in fb.sorted, and per tile the positions in it of
// the splats that reach the tile (fb.binned, ascending: depth order). Tile lists hold 4-byte positions, not the
// 48-byte records: scattered over a thousand tiles, record copies cost more than gathering them back per tile.
// The sort runs on the calling thread: a parallel one needs about ten barriers, and a barrier stalls for as long
// as any other process holds one of the cores.
void bin_frame(const Splat* s, int n, int tiles_x, int tiles, FrameBins& fb, int threads) {
    sort_visible_by_depth(s, n, fb);
    const int m = int(fb.order.size());
    fb.sorted.resize(m);
    fb.rects.resize(m);
    fb.counts.assign(size_t(threads) * tiles, 0);
    fb.tile_offsets.assign(tiles + 1, 0);
#pragma omp parallel num_threads(threads)
    {
        const int t = omp_get_thread_num(), nt = omp_get_num_threads();
        const int i0 = int(int64_t(m) * t / nt), i1 = int(int64_t(m) * (t + 1) / nt);
        uint32_t* cnt = fb.counts.data() + size_t(t) * tiles;
        const uint32_t* order = fb.order.data();
        constexpr int kAhead = 64;  // depth order visits the splats at random: prefetch (16 was too few)
        for (int i = i0; i < i1; ++i) {
            if (i + kAhead < i1) __builtin_prefetch(&s[order[i + kAhead]]);
            const Splat& g = s[order[i]];
            fb.sorted[i] = g.t;
            const TileRect r = fb.rects[i] = tile_rect(g);
            for (int ty = r.y0; ty <= r.y1; ++ty)
                for (int tx = r.x0; tx <= r.x1; ++tx) ++cnt[ty * tiles_x + tx];
        }
#pragma omp barrier
#pragma omp single
        {
            // Per tile, thread t's entries follow thread t-1's: depth order is kept.
            uint32_t run = 0;
            for (int tile = 0; tile < tiles; ++tile) {
                fb.tile_offsets[tile] = run;
                for (int u = 0; u < nt; ++u) {
                    uint32_t& c = fb.counts[size_t(u) * tiles + tile];
                    const uint32_t c0 = c;
                    c = run;
                    run += c0;
                }
            }
            fb.tile_offsets[tiles] = run;
            fb.binned.resize(run);
        }
        uint32_t* binned = fb.binned.data();
        for (int i = i0; i < i1; ++i) {
            const TileRect r = fb.rects[i];
            for (int ty = r.y0; ty <= r.y1; ++ty)
                for (int tx = r.x0; tx <= r.x1; ++tx) binned[cnt[ty * tiles_x + tx]++] = uint32_t(i);
        }
    }
}

namespace {

// Depth-sort, bin and composite B frames of projected splats ([B, n] each); returns the binning time (ms).
double rasterize_splats(const Splat* splats, int n, int B, const Cam* cams, const float* bg, const FrameOut& out,
                        const Kernels& k, int threads, unsigned flags) {
    const auto t0 = Clock::now();
    static thread_local std::vector<FrameBins> bins_tls;  // the caller's; worker threads use it by reference
    std::vector<FrameBins>& bins = bins_tls;
    if (int(bins.size()) < B) bins.resize(B);
    const int W = cams[0].width, H = cams[0].height;
    const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile, tiles = tiles_x * tiles_y;
    if (B >= 2 && threads >= 2) {  // a frame per thread: no barriers inside a frame's sort and binning
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
        for (int b = 0; b < B; ++b) bin_frame(splats + size_t(b) * n, n, tiles_x, tiles, bins[b], 1);
    } else {
        for (int b = 0; b < B; ++b) bin_frame(splats + size_t(b) * n, n, tiles_x, tiles, bins[b], threads);
    }
    const double bin_ms = ms_since(t0);
    const int jobs = B * tiles;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 4)
    for (int job = 0; job < jobs; ++job) {
        const int b = job / tiles, t = job % tiles;
        const FrameBins& fb = bins[b];
        const size_t pix = size_t(b) * W * H;
        TileOut o;
        if (out.rgb != nullptr) o.rgb = out.rgb + pix * 3;
        if (out.alpha != nullptr) o.alpha = out.alpha + pix;
        if (out.depth != nullptr) o.depth = out.depth + pix;
        if (out.rgba8 != nullptr) o.rgba8 = out.rgba8 + pix * 4;
        const uint32_t o0 = fb.tile_offsets[t];
        k.raster_tile(fb.sorted.data(), fb.binned.data() + o0, int(fb.tile_offsets[t + 1] - o0), t % tiles_x,
                      t / tiles_x, cams[b], bg + 3 * b, o, flags);
    }
    return bin_ms;
}

constexpr int kChunk = 512;  // Gaussians per parallel work item

}  // namespace

std::vector<std::string> available_isas() {
    std::vector<std::string> out{"scalar"};
#ifdef BS_HAVE_AVX2
    if (cpu_has("avx2")) out.push_back("avx2");
#endif
#ifdef BS_HAVE_AVX512
    if (cpu_has("avx512")) out.push_back("avx512");
#endif
    return out;
}

const Kernels& select_kernels(const std::string& isa) {
    const auto avail = available_isas();
    const std::string pick = isa == "auto" || isa.empty() ? avail.back() : isa;
    if (std::find(avail.begin(), avail.end(), pick) == avail.end()) {
        std::string msg = "SIMD path '" + isa + "' is not available on this CPU/build; available:";
        for (const auto& a : avail) msg += " " + a;
        throw std::invalid_argument(msg);
    }
#ifdef BS_HAVE_AVX512
    if (pick == "avx512") return avx512::kernels();
#endif
#ifdef BS_HAVE_AVX2
    if (pick == "avx2") return avx2::kernels();
#endif
    return scalar::kernels();
}

Timings render_fused(const AvatarView& av, const float* psi, const float* rot, const float* eyelids, const Cam* cams,
                     int B, const float* bg, const FrameOut& out, const Kernels& k, int threads, unsigned flags) {
    Timings tm;
    static thread_local std::vector<float> A_tls, pose_feat_tls;
    static thread_local std::vector<Splat> splats_tls;
    // References to the calling thread's buffers: inside parallel regions they name these, not the workers' own.
    std::vector<float>&A = A_tls, &pose_feat = pose_feat_tls;
    std::vector<Splat>& splats = splats_tls;
    A.assign(size_t(B) * av.J * 12, 0.0f);
    pose_feat.assign(size_t(B) * std::max(av.Ppad, 1), 0.0f);
    for (int b = 0; b < B; ++b) {
        const float* r = rot + size_t(b) * av.J * 9;
        joint_transforms(av, r, A.data() + size_t(b) * av.J * 12);
        for (int j = 1; j < av.J; ++j)
            for (int e = 0; e < 9; ++e)
                pose_feat[size_t(b) * av.Ppad + (j - 1) * 9 + e] = r[j * 9 + e] - ((e % 4 == 0) ? 1.0f : 0.0f);
    }
    splats.resize(size_t(B) * av.n_total);

    // Blend, then deform and project, a chunk of Gaussians at a time: the blended rows stay in cache, and the
    // memory-bound blend of one thread overlaps the compute-bound projection of the other.
    constexpr int kFuse = 256;
    const int chunks = (av.n_total + kFuse - 1) / kFuse;
    std::vector<double> blend_s(threads, 0.0), deform_s(threads, 0.0);
    const auto t0 = Clock::now();
#pragma omp parallel num_threads(threads)
    {
        static thread_local std::vector<float> rows_tls;  // this thread's own
        std::vector<float>& rows = rows_tls;
        rows.resize(size_t(std::min(B, kMaxBatch)) * kFuse * av.Dp);
        const int tid = omp_get_thread_num();
#pragma omp for schedule(dynamic, 2)  // chunks differ in cost: the mouth has no blendshapes
        for (int c = 0; c < chunks; ++c) {
            const int n0 = c * kFuse, n1 = std::min(av.n_total, n0 + kFuse);
            for (int b0 = 0; b0 < B; b0 += kMaxBatch) {
                const int nb = std::min(kMaxBatch, B - b0);
                const auto c0 = Clock::now();
                k.blend(av, psi + size_t(b0) * av.K, pose_feat.data() + size_t(b0) * av.Ppad,
                        eyelids + size_t(b0) * 2, nb, rows.data(), kFuse, n0, n1);
                const auto c1 = Clock::now();
                for (int b = 0; b < nb; ++b)
                    k.deform_project(av, rows.data() + size_t(b) * kFuse * av.Dp, A.data() + size_t(b0 + b) * av.J * 12,
                                     cams[b0 + b], splats.data() + size_t(b0 + b) * av.n_total, n0, n1);
                blend_s[tid] += std::chrono::duration<double, std::milli>(c1 - c0).count();
                deform_s[tid] += ms_since(c1);
            }
        }
    }
    // The fused stage's wall time, split between blend and deform in proportion to the threads' time in each.
    const double fused_ms = ms_since(t0);
    double bsum = 0.0, dsum = 0.0;
    for (int t = 0; t < threads; ++t) bsum += blend_s[t], dsum += deform_s[t];
    tm.blend_ms = bsum + dsum > 0.0 ? fused_ms * bsum / (bsum + dsum) : 0.0;
    tm.lbs_ms = fused_ms - tm.blend_ms;

    const auto t1 = Clock::now();
    tm.bin_ms = rasterize_splats(splats.data(), av.n_total, B, cams, bg, out, k, threads, flags);
    tm.raster_ms = ms_since(t1);
    return tm;
}

Timings render_posed(const PosedView& pv, const Cam* cams, int B, const float* bg, const FrameOut& out,
                     const Kernels& k, int threads, unsigned flags) {
    Timings tm;
    static thread_local std::vector<Splat> splats_tls;
    std::vector<Splat>& splats = splats_tls;
    splats.resize(size_t(B) * pv.N);
    const int chunks = (pv.N + kChunk - 1) / kChunk;
    auto t0 = Clock::now();
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int job = 0; job < B * chunks; ++job) {
        const int b = job / chunks, c = job % chunks;
        const int n0 = c * kChunk, n1 = std::min(pv.N, n0 + kChunk);
        k.project_posed(pv, b, cams[b], splats.data() + size_t(b) * pv.N, n0, n1);
    }
    tm.lbs_ms = ms_since(t0);
    t0 = Clock::now();
    tm.bin_ms = rasterize_splats(splats.data(), pv.N, B, cams, bg, out, k, threads, flags);
    tm.raster_ms = ms_since(t0);
    return tm;
}

}  // namespace bs
