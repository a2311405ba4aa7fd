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

// A run of splats sorted by depth: positions into the frame's splats and their depth keys (the float's bits).
struct SortedRun {
    const uint32_t* idx;
    const uint32_t* key;
    int m;
};

// The visible splats among s[i0, i1) sorted by depth, ties in index order: a stable LSD radix sort of 11 bits a
// pass over the bits of the positive float depths (whose order is their bits' order) less the smallest: only as
// many passes as the run's range of bits needs (two for a head, whose depths span a narrow range). idx, key and
// their tmp twins hold i1 - i0 entries, hist 2048; the run ends in one pair or the other.
SortedRun sort_visible_by_depth(const Splat* s, int i0, int i1, uint32_t* idx, uint32_t* key, uint32_t* tmp_idx,
                                uint32_t* tmp_key, uint32_t* hist) {
    constexpr int kBuckets = 2048;
    int m = 0;
    uint32_t lo = UINT32_MAX, hi = 0;
    for (int i = i0; i < i1; ++i) {
        if (!(s[i].x0 < s[i].x1)) continue;
        uint32_t k;
        std::memcpy(&k, &s[i].t.depth, 4);
        idx[m] = uint32_t(i), key[m] = k, lo = std::min(lo, k), hi = std::max(hi, k);
        ++m;
    }
    const uint32_t range = m > 0 ? hi - lo : 0;
    for (int sh = 0; sh < 32 && (sh == 0 || (range >> sh) != 0); sh += 11) {
        std::fill(hist, hist + kBuckets, 0u);
        for (int j = 0; j < m; ++j) ++hist[((key[j] - lo) >> sh) & (kBuckets - 1)];
        uint32_t run = 0;
        for (int b = 0; b < kBuckets; ++b) {
            const uint32_t c = hist[b];
            hist[b] = run;
            run += c;
        }
        for (int j = 0; j < m; ++j) {
            const uint32_t dst = hist[((key[j] - lo) >> sh) & (kBuckets - 1)]++;
            tmp_idx[dst] = idx[j], tmp_key[dst] = key[j];
        }
        std::swap(idx, tmp_idx);
        std::swap(key, tmp_key);
    }
    return {idx, key, m};
}

// Positions d0 <= d < d1 of the merge of runs a and b into out[d0, d1). All of a's splats precede b's in index
// order, so a wins ties: the merge is the stable sort of both. Merge path: d0's split found by binary search.
void merge_runs(const SortedRun& a, const SortedRun& b, int d0, int d1, uint32_t* out) {
    int lo = std::max(0, d0 - b.m), hi = std::min(d0, a.m);
    while (lo < hi) {  // the most of a's entries among the first d0: a[i - 1] goes before b[d0 - i]
        const int mid = (lo + hi + 1) / 2;
        if (a.key[mid - 1] <= b.key[d0 - mid])
            lo = mid;
        else
            hi = mid - 1;
    }
    int ia = lo, ib = d0 - lo;
    for (int d = d0; d < d1; ++d) {
        const bool take_a = ib == b.m || (ia < a.m && a.key[ia] <= b.key[ib]);
        out[d] = take_a ? a.idx[ia++] : b.idx[ib++];
    }
}

constexpr int kMinSortHalf = 4096;  // splats a half needs before two threads sort (a barrier costs more below)

}  // namespace

// Visible splats of one frame in depth order (ties by index) in fb.sorted, and per tile the positions in it of
// the splats that reach the tile (fb.binned, ascending: depth order). Tile lists hold 4-byte positions, not the
// 48-byte records: scattered over a thousand tiles, record copies cost more than gathering them back per tile.
// With one thread (a batch's frames bin a frame per thread) the sort runs alone; with more, two threads sort the
// two halves of the splats and every thread merges its share of the depth order as it gathers the records (the
// same order, bit for bit, in about half the time: one stream's other core no longer waits through the sort).
void bin_frame(const Splat* s, int n, int tiles_x, int tiles, FrameBins& fb, int threads) {
    constexpr int kBuckets = 2048;
    fb.order.resize(n), fb.keys.resize(n), fb.tmp.resize(n), fb.tmp_keys.resize(n);
    fb.hist.resize(size_t(2) * kBuckets);
    SortedRun runs[2] = {};
    const int halves = threads >= 2 && n >= 2 * kMinSortHalf ? 2 : 1;
    const auto sort_half = [&](int u) {
        const int i0 = int(int64_t(n) * u / halves), i1 = int(int64_t(n) * (u + 1) / halves);
        runs[u] = sort_visible_by_depth(s, i0, i1, fb.order.data() + i0, fb.keys.data() + i0, fb.tmp.data() + i0,
                                        fb.tmp_keys.data() + i0, fb.hist.data() + size_t(u) * kBuckets);
    };
    if (halves == 1) sort_half(0);
    int visible = runs[0].m;  // two halves: known once both are sorted
    const uint32_t* order = runs[0].idx;
    fb.counts.assign(size_t(threads) * tiles, 0);
    fb.tile_offsets.assign(tiles + 1, 0);
    if (halves == 1) fb.sorted.resize(visible), fb.rects.resize(visible);
#pragma omp parallel num_threads(threads)
    {
        const int t = omp_get_thread_num(), nt = omp_get_num_threads();
        if (halves == 2) {
            if (t < 2) sort_half(t);
#pragma omp barrier
#pragma omp single
            {
                visible = runs[0].m + runs[1].m;
                fb.merged.resize(visible);
                order = fb.merged.data();
                fb.sorted.resize(visible);
                fb.rects.resize(visible);
            }
        }
        const int i0 = int(int64_t(visible) * t / nt), i1 = int(int64_t(visible) * (t + 1) / nt);
        if (halves == 2) merge_runs(runs[0], runs[1], i0, i1, fb.merged.data());
        uint32_t* cnt = fb.counts.data() + size_t(t) * tiles;
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
