// The per-frame kernels, written once over a SIMD wrapper V (simd.hpp) and compiled once per instruction set
// (kernels_scalar.cpp, kernels_avx2.cpp, kernels_avx512.cpp define V and BS_NS, then include this file).
// Semantics: docs/method.md sections 2 and 9, exactly as render_core/deform.py and render_core/raster/reference.py.

#include <algorithm>
#include <cmath>
#include <cstring>
#include <type_traits>
#include <vector>

#include "common.hpp"
#include "simd.hpp"

namespace bs {
namespace BS_NS {

using F = V::F;
using M = V::M;
constexpr int W = V::W;
constexpr int kMaxLanes = 16;

// ------------------------------------------------------------------------------------------------ blend

// Pair values as stored: float, uint16_t (fp16 bits) or int8_t (times their scales: PairsView).
template <class T>
constexpr bool kQuantized = std::is_same_v<T, int8_t>;

// The weights of int8 geometry residuals in the lanes of columns d..d + W: 1/256 in the position columns, 0 elsewhere
// (those lanes load the next pairs' residuals).
static inline F residual_weights(int d) {
    const M position = V::lt(V::iota() + V::set1(float(d)), V::set1(float(kPositionColumns)));
    return V::select(position, V::set1(kResidualStep), V::set1(0.0f));
}

// int8 pair j's columns d..d + W in steps of their scales, exactly: q, plus residual / 256 in the position columns.
static inline F pair_steps(const PairsView& p, int j, int d) {
    const F q = V::load(static_cast<const int8_t*>(p.vals) + size_t(j) * p.len + d);
    if (p.residual == nullptr || d >= kPositionColumns) return q;
    return V::fma(V::load(p.residual + size_t(j) * kPositionColumns + d), residual_weights(d), q);
}

// Values d..d + W of pair j (blendshape k) in float32: as stored, or int8 steps times their scale exactly as
// packed.py dequantises them (one rounding), so batches render an int8 avatar as its dequantised fp32 twin, bit for
// bit.
template <class T>
static inline F pair_values(const PairsView& p, int j, int k, int d) {
    if constexpr (kQuantized<T>) {
        return pair_steps(p, j, d) * V::load(p.scale + size_t(k) * ((p.len + 15) & ~15) + d);
    } else {
        return V::load(static_cast<const T*>(p.vals) + size_t(j) * p.len + d);
    }
}

// acc[g][d..d + NV W) += sum_j psi[g][col[j]] vals[j][d..] for GB frames g (acc rows DP floats apart): NV vectors
// of accumulators per frame stay in registers while the pairs stream by (int8 values dequantised once per pair
// for the GB frames).
template <class T, int DP, int GB, int NV>
static inline void blend_slice(const PairsView& p, int K, const float* psi, int j0, int j1, float* acc, int d) {
    F a[GB][NV];
    for (int g = 0; g < GB; ++g)
        for (int v = 0; v < NV; ++v) a[g][v] = V::load(acc + g * DP + d + v * W);
    for (int j = j0; j < j1; ++j) {
        const int k = p.col[j];
        F x[NV];
        for (int v = 0; v < NV; ++v) x[v] = pair_values<T>(p, j, k, d + v * W);
        for (int g = 0; g < GB; ++g) {
            const F w = V::set1(psi[g * K + k]);
            for (int v = 0; v < NV; ++v) a[g][v] = V::fma(w, x[v], a[g][v]);
        }
    }
    for (int g = 0; g < GB; ++g)
        for (int v = 0; v < NV; ++v) V::store(acc + g * DP + d + v * W, a[g][v]);
}

// acc[g][0..CW) += sum_j psi[g][col[j]] vals[j] for GB frames g, two vectors of the row at a time (and one for
// the last vector when CW is an odd number of vectors, e.g. 16 or 48 floats with 16 lanes).
template <class T, int DP, int CW, int GB>
static inline void blend_group(const PairsView& p, int K, const float* psi, int j0, int j1, float* acc) {
    static_assert(CW % W == 0, "pair rows are read as whole vectors");
    if constexpr (W >= 16 && CW / W <= 4) {  // 32 registers: the whole row's accumulators of GB frames fit
        blend_slice<T, DP, GB, CW / W>(p, K, psi, j0, j1, acc, 0);
        return;
    }
    int d = 0;
    for (; d + 2 * W <= CW; d += 2 * W) blend_slice<T, DP, GB, 2>(p, K, psi, j0, j1, acc, d);
    if constexpr (CW % (2 * W) != 0) blend_slice<T, DP, GB, 1>(p, K, psi, j0, j1, acc, d);
}

// One frame, int8 values: acc[0..CW) += sum_j ws[col[j]] steps[j] (pair_steps), with ws [K, CW] the frame's
// weighted scales psi[k] scale[k][d] (weighted_scales): per value one conversion and one FMA, as the float paths,
// from a quarter (of fp32) or half (of fp16) of the bytes, the row's accumulators in registers. Lanes past len
// have weight 0.
template <int CW>
static inline void blend_pairs_ws(const PairsView& p, const float* ws, int j0, int j1, float* acc) {
    constexpr int NV = CW / W;
    F a[NV];
    for (int v = 0; v < NV; ++v) a[v] = V::load(acc + v * W);
    for (int j = j0; j < j1; ++j) {
        const float* w = ws + size_t(p.col[j]) * CW;
#pragma GCC unroll 16
        for (int v = 0; v < NV; ++v) a[v] = V::fma(V::load(w + v * W), pair_steps(p, j, v * W), a[v]);
    }
    for (int v = 0; v < NV; ++v) V::store(acc + v * W, a[v]);
}

// The pairs of face Gaussian n, CW columns wide, added to acc (frame b's columns at acc + b DP). ws: one int8
// frame's weighted scales [K, CW] (null: none).
template <class T, int DP, int CW>
static inline void blend_pairs(const PairsView& p, int K, const float* psi, const float* ws, int B, int n,
                               float* acc) {
    const int j0 = p.row_ptr[n], j1 = p.row_ptr[n + 1];
    if (j0 == j1) return;
    if constexpr (kQuantized<T>) {
        if (ws != nullptr) return blend_pairs_ws<CW>(p, ws, j0, j1, acc);
    } else if (B == 1) {  // the whole row's accumulators in registers
        const T* vals = static_cast<const T*>(p.vals);
        for (int j = j0; j < j1; ++j) {
            const F w = V::set1(psi[p.col[j]]);
            const T* v = vals + size_t(j) * p.len;
#pragma GCC unroll 16
            for (int d = 0; d < CW; d += W) V::store(acc + d, V::fma(w, V::load(v + d), V::load(acc + d)));
        }
        return;
    }
    // Groups of up to 4 frames x 2 vectors of accumulators in registers; the row stays in L1.
    int b = 0;
    for (; b + 4 <= B; b += 4) blend_group<T, DP, CW, 4>(p, K, psi + b * K, j0, j1, acc + b * DP);
    for (; b < B; ++b) blend_group<T, DP, CW, 1>(p, K, psi + b * K, j0, j1, acc + b * DP);
}

// Weighted scales of one frame of an int8 avatar, ws [K, DP]: the geometry's psi[k] scale[k][0..16), then the
// colour's psi[k] scale[k][0..DP - 16) (at ws + 16 K). Made once per blend call (K DP products, against the
// pairs' K N (11 + 3C) values) when they fit kWeightedScales floats; else null (the batched path, which
// dequantises each pair instead).
constexpr size_t kWeightedScales = size_t(1) << 15;  // 128 KB: 512 blendshapes at 3C = 48

template <int DP>
static const float* weighted_scales(const AvatarView& av, const float* psi) {
    if (size_t(av.K) * DP > kWeightedScales) return nullptr;
    static thread_local std::vector<float> ws_tls;
    std::vector<float>& ws = ws_tls;
    ws.resize(size_t(av.K) * DP);
    constexpr int kGeo = 16, kCol = DP - kGeo;
    float* geo = ws.data();
    float* col = geo + size_t(av.K) * kGeo;
    for (int k = 0; k < av.K; ++k) {
        for (int d = 0; d < kGeo; ++d) geo[k * kGeo + d] = psi[k] * av.geometry.scale[k * kGeo + d];
        for (int d = 0; d < kCol; ++d) col[k * kCol + d] = psi[k] * av.color.scale[k * kCol + d];
    }
    return ws.data();
}

// A block of nl <= W Gaussians' blended rows, tile[lane][frame][DP] (geometry in columns 0..10, colour from 16),
// written lane-interleaved ([value][lane], the 11 + sh values) for each of B frames, as deform_project loads them:
// frame b's block at out + b * frame_stride. With AVX-512 by 16 x 16 transposes (64 shuffles for 256 values, where
// one load and one scalar store each took about half of the blend's time; AVX2: 8 x 8, 24 shuffles for 64); lanes
// past nl are left as they were.
static inline void write_block(const float* tile, int B, int DP, int sh, int nl, float* out, size_t frame_stride) {
#if defined(BS_ISA_AVX512)
    const __mmask16 lanes = __mmask16((1u << nl) - 1u);
    for (int b = 0; b < B; ++b) {
        float* o = out + size_t(b) * frame_stride;
        for (int c0 = 0; c0 < DP && (c0 == 0 || c0 - 16 < sh); c0 += 16) {
            __m512 r[16], u[16];
            for (int i = 0; i < 16; ++i) r[i] = _mm512_load_ps(tile + (size_t(i) * B + b) * DP + c0);
            for (int i = 0; i < 16; i += 2)
                u[i] = _mm512_unpacklo_ps(r[i], r[i + 1]), u[i + 1] = _mm512_unpackhi_ps(r[i], r[i + 1]);
            for (int i = 0; i < 16; i += 4)  // r[i + k]'s 128-bit lane j: rows i..i+3 of column 4j + k
                for (int k = 0; k < 2; ++k) {
                    const __m512d a = _mm512_castps_pd(u[i + k]), c = _mm512_castps_pd(u[i + k + 2]);
                    r[i + 2 * k] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
                    r[i + 2 * k + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
                }
            __m512 col[16];
            for (int k = 0; k < 4; ++k) {
                const __m512 v0 = _mm512_shuffle_f32x4(r[k], r[4 + k], 0x44), v1 = _mm512_shuffle_f32x4(r[k], r[4 + k], 0xEE);
                const __m512 w0 = _mm512_shuffle_f32x4(r[8 + k], r[12 + k], 0x44);
                const __m512 w1 = _mm512_shuffle_f32x4(r[8 + k], r[12 + k], 0xEE);
                col[k] = _mm512_shuffle_f32x4(v0, w0, 0x88), col[4 + k] = _mm512_shuffle_f32x4(v0, w0, 0xDD);
                col[8 + k] = _mm512_shuffle_f32x4(v1, w1, 0x88), col[12 + k] = _mm512_shuffle_f32x4(v1, w1, 0xDD);
            }
            const int first = c0 == 0 ? 0 : 11 + c0 - 16, count = c0 == 0 ? 11 : std::min(16, sh - (c0 - 16));
            for (int j = 0; j < count; ++j) _mm512_mask_storeu_ps(o + size_t(first + j) * W, lanes, col[j]);
        }
    }
#elif defined(BS_ISA_AVX2)
    alignas(32) int32_t lane_on[8];
    for (int l = 0; l < 8; ++l) lane_on[l] = l < nl ? -1 : 0;
    const __m256i lanes = _mm256_load_si256(reinterpret_cast<const __m256i*>(lane_on));
    for (int b = 0; b < B; ++b) {
        float* o = out + size_t(b) * frame_stride;
        for (int c0 = 0; c0 < DP && (c0 < 16 || c0 - 16 < sh); c0 += 8) {
            __m256 r[8], t[8], col[8];
            for (int i = 0; i < 8; ++i) r[i] = _mm256_load_ps(tile + (size_t(i) * B + b) * DP + c0);
            for (int i = 0; i < 8; i += 2)
                t[i] = _mm256_unpacklo_ps(r[i], r[i + 1]), t[i + 1] = _mm256_unpackhi_ps(r[i], r[i + 1]);
            for (int h = 0; h < 8; h += 4) {  // r[h + k]'s 128-bit lane j: rows h..h+3 of column 4j + k
                r[h] = _mm256_shuffle_ps(t[h], t[h + 2], 0x44), r[h + 1] = _mm256_shuffle_ps(t[h], t[h + 2], 0xEE);
                r[h + 2] = _mm256_shuffle_ps(t[h + 1], t[h + 3], 0x44);
                r[h + 3] = _mm256_shuffle_ps(t[h + 1], t[h + 3], 0xEE);
            }
            for (int k = 0; k < 4; ++k)
                col[k] = _mm256_permute2f128_ps(r[k], r[4 + k], 0x20), col[4 + k] = _mm256_permute2f128_ps(r[k], r[4 + k], 0x31);
            const int first = c0 < 16 ? c0 : 11 + c0 - 16;
            const int count = c0 < 16 ? std::min(8, 11 - c0) : std::min(8, sh - (c0 - 16));
            for (int j = 0; j < count; ++j) _mm256_maskstore_ps(o + size_t(first + j) * W, lanes, col[j]);
        }
    }
#else
    for (int l = 0; l < nl; ++l)
        for (int b = 0; b < B; ++b) {
            float* o = out + size_t(b) * frame_stride + l;
            const float* a = tile + (size_t(l) * B + b) * DP;
            for (int d = 0; d < 11; ++d) o[d * W] = a[d];
            for (int d = 0; d < sh; ++d) o[(11 + d) * W] = a[16 + d];
        }
#endif
}

template <class T, class TP, int DP>
static void blend_t(const AvatarView& av, const float* psi, const float* pose_feat, const float* eyelids, int B,
                    float* out, int out_stride, int n0, int n1) {
    constexpr int kGeo = 16;  // geometry columns 0..15 (11 used), then colour columns
    static thread_local std::vector<float> tile_tls;  // [W lanes][B frames][DP]: a block's rows, 64-byte aligned
    std::vector<float>& tile_buf = tile_tls;
    if (tile_buf.size() < size_t(W) * B * DP + 16) tile_buf.resize(size_t(W) * B * DP + 16);
    float* const tile = reinterpret_cast<float*>((reinterpret_cast<uintptr_t>(tile_buf.data()) + 63) & ~uintptr_t(63));
    const TP* pc = static_cast<const TP*>(av.pc);
    const int sh = 3 * av.C;
    const float* ws = nullptr;
    if constexpr (kQuantized<T>) ws = B == 1 ? weighted_scales<DP>(av, psi) : nullptr;
    const float* ws_color = ws != nullptr ? ws + size_t(av.K) * kGeo : nullptr;
    bool any_pose[kMaxBatch];
    for (int b = 0; b < B; ++b) {
        any_pose[b] = false;
        for (int p = 0; p < av.P; ++p) any_pose[b] |= pose_feat[b * av.Ppad + p] != 0.0f;
    }
    for (int n = n0; n < n1; ++n) {
        const int i = n - n0, lane = i % W;
        float* const acc = tile + size_t(lane) * B * DP;  // frame b's row at acc + b DP
        const float* base = av.base + size_t(n) * DP;
        for (int b = 0; b < B; ++b) std::memcpy(acc + b * DP, base, sizeof(float) * DP);
        if (n < av.n_face) {
            blend_pairs<T, DP, kGeo>(av.geometry, av.K, psi, ws, B, n, acc);
            blend_pairs<T, DP, DP - kGeo>(av.color, av.K, psi, ws_color, B, n, acc + kGeo);
        }
        if (pc != nullptr && n < av.n_face) {
            for (int b = 0; b < B; ++b) {
                if (!any_pose[b]) continue;
                const float* f = pose_feat + b * av.Ppad;
                for (int c = 0; c < 3; ++c) {
                    const TP* row = pc + (size_t(n) * 3 + c) * av.Ppad;
                    F s = V::set1(0.0f);
                    for (int p = 0; p < av.Ppad; p += W) s = V::fma(V::load(f + p), V::load(row + p), s);
                    acc[b * DP + c] += V::hsum(s);
                }
            }
        }
        if (av.eyelid != nullptr && n < av.n_face) {
            const float* e = av.eyelid + size_t(n) * 6;
            for (int b = 0; b < B; ++b) {
                const float e0 = eyelids[b * 2], e1 = eyelids[b * 2 + 1];
                if (e0 == 0.0f && e1 == 0.0f) continue;
                for (int c = 0; c < 3; ++c) acc[b * DP + c] += e0 * e[c] + e1 * e[3 + c];
            }
        }
        // Lane-interleaved blocks of W Gaussians ([block][d][lane], d over the 11 + 3C used values), what
        // deform_project loads as vectors: written a block at a time.
        if (lane == W - 1 || n == n1 - 1)
            write_block(tile, B, DP, sh, lane + 1, out + size_t(i / W) * DP * W, size_t(out_stride) * DP);
    }
}

template <class T, class TP>
static void blend_dp(const AvatarView& av, const float* psi, const float* pf, const float* el, int B, float* out,
                     int stride, int n0, int n1) {
    switch (av.Dp) {
        case 32: return blend_t<T, TP, 32>(av, psi, pf, el, B, out, stride, n0, n1);
        case 48: return blend_t<T, TP, 48>(av, psi, pf, el, B, out, stride, n0, n1);
        default: return blend_t<T, TP, 64>(av, psi, pf, el, B, out, stride, n0, n1);
    }
}

static void blend(const AvatarView& av, const float* psi, const float* pf, const float* el, int B, float* out,
                  int stride, int n0, int n1) {
    switch (av.storage) {  // pair values, pose correctives
        case Storage::kF16: return blend_dp<uint16_t, uint16_t>(av, psi, pf, el, B, out, stride, n0, n1);
        case Storage::kI8: return blend_dp<int8_t, uint16_t>(av, psi, pf, el, B, out, stride, n0, n1);
        default: return blend_dp<float, float>(av, psi, pf, el, B, out, stride, n0, n1);
    }
}

// ------------------------------------------------------------------------------------------------ geometry

struct Mat3 {
    F m[9];
};

static inline F dot3(F a0, F a1, F a2, F b0, F b1, F b2) { return V::fma(a0, b0, V::fma(a1, b1, a2 * b2)); }

// R <- (R + R^-T) / 2, three times (render_core.rotation.orthogonalize).
static inline Mat3 orthogonalize(Mat3 r) {
    for (int it = 0; it < 3; ++it) {
        const F* m = r.m;
        F c0[3] = {m[4] * m[8] - m[5] * m[7], m[5] * m[6] - m[3] * m[8], m[3] * m[7] - m[4] * m[6]};
        F c1[3] = {m[7] * m[2] - m[8] * m[1], m[8] * m[0] - m[6] * m[2], m[6] * m[1] - m[7] * m[0]};
        F c2[3] = {m[1] * m[5] - m[2] * m[4], m[2] * m[3] - m[0] * m[5], m[0] * m[4] - m[1] * m[3]};
        F det = dot3(m[0], m[1], m[2], c0[0], c0[1], c0[2]);
        F h = V::set1(0.5f) / det;
        Mat3 o;
        for (int j = 0; j < 3; ++j) {
            o.m[j] = V::fma(c0[j], h, V::set1(0.5f) * m[j]);
            o.m[3 + j] = V::fma(c1[j], h, V::set1(0.5f) * m[3 + j]);
            o.m[6 + j] = V::fma(c2[j], h, V::set1(0.5f) * m[6 + j]);
        }
        r = o;
    }
    return r;
}

static inline void normalize4(F q[4]) {
    F n = V::sqrt(V::fma(q[0], q[0], V::fma(q[1], q[1], V::fma(q[2], q[2], q[3] * q[3]))));
    F inv = V::set1(1.0f) / V::max(n, V::set1(1e-12f));
    for (int i = 0; i < 4; ++i) q[i] = q[i] * inv;
}

// Shepperd's method, the largest candidate first in ties (render_core.rotation.matrix_to_quat).
static inline void matrix_to_quat(const Mat3& r, F q[4]) {
    const F* m = r.m;
    const F one = V::set1(1.0f);
    F cand[4][4] = {
        {one + m[0] + m[4] + m[8], m[7] - m[5], m[2] - m[6], m[3] - m[1]},
        {m[7] - m[5], one + m[0] - m[4] - m[8], m[1] + m[3], m[2] + m[6]},
        {m[2] - m[6], m[1] + m[3], one - m[0] + m[4] - m[8], m[5] + m[7]},
        {m[3] - m[1], m[2] + m[6], m[5] + m[7], one - m[0] - m[4] + m[8]},
    };
    F best[4] = {cand[0][0], cand[0][1], cand[0][2], cand[0][3]};
    F bd = cand[0][0];
    for (int i = 1; i < 4; ++i) {
        M gt = V::gt(cand[i][i], bd);
        for (int c = 0; c < 4; ++c) best[c] = V::select(gt, cand[i][c], best[c]);
        bd = V::select(gt, cand[i][i], bd);
    }
    F s = V::set1(0.5f) / V::sqrt(V::max(bd, V::set1(1e-12f)));
    for (int c = 0; c < 4; ++c) q[c] = best[c] * s;
    normalize4(q);
    M neg = V::lt(q[0], V::set1(0.0f));
    for (int c = 0; c < 4; ++c) q[c] = V::select(neg, -q[c], q[c]);
}

static inline Mat3 quat_to_matrix(const F q[4]) {
    F w = q[0], x = q[1], y = q[2], z = q[3];
    const F one = V::set1(1.0f), two = V::set1(2.0f);
    Mat3 r;
    r.m[0] = one - two * (y * y + z * z);
    r.m[1] = two * (x * y - w * z);
    r.m[2] = two * (x * z + w * y);
    r.m[3] = two * (x * y + w * z);
    r.m[4] = one - two * (x * x + z * z);
    r.m[5] = two * (y * z - w * x);
    r.m[6] = two * (x * z - w * y);
    r.m[7] = two * (y * z + w * x);
    r.m[8] = one - two * (x * x + y * y);
    return r;
}

static inline void quat_mul(const F a[4], const F b[4], F o[4]) {
    o[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    o[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    o[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    o[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

// Real SH basis (3DGS / gsplat constants and signs) at direction (x, y, z), dotted with coefficients.
static inline void eval_sh(const float* buf, int C, F x, F y, F z, F rgb[3]) {
    auto coef = [&](int k, int c) { return V::load(buf + (11 + k * 3 + c) * W); };
    F basis[16];
    basis[0] = V::set1(0.28209479177387814f);
    if (C > 1) {
        const F c1 = V::set1(0.4886025119029199f);
        basis[1] = -c1 * y;
        basis[2] = c1 * z;
        basis[3] = -c1 * x;
    }
    if (C > 4) {
        F xx = x * x, yy = y * y, zz = z * z;
        basis[4] = V::set1(1.0925484305920792f) * x * y;
        basis[5] = V::set1(-1.0925484305920792f) * y * z;
        basis[6] = V::set1(0.31539156525252005f) * (V::set1(2.0f) * zz - xx - yy);
        basis[7] = V::set1(-1.0925484305920792f) * x * z;
        basis[8] = V::set1(0.5462742152960396f) * (xx - yy);
        if (C > 9) {
            basis[9] = V::set1(-0.5900435899266435f) * y * (V::set1(3.0f) * xx - yy);
            basis[10] = V::set1(2.890611442640554f) * x * y * z;
            basis[11] = V::set1(-0.4570457994644658f) * y * (V::set1(4.0f) * zz - xx - yy);
            basis[12] = V::set1(0.3731763325901154f) * z * (V::set1(2.0f) * zz - V::set1(3.0f) * xx - V::set1(3.0f) * yy);
            basis[13] = V::set1(-0.4570457994644658f) * x * (V::set1(4.0f) * zz - xx - yy);
            basis[14] = V::set1(1.445305721320277f) * z * (xx - yy);
            basis[15] = V::set1(-0.5900435899266435f) * x * (xx - V::set1(3.0f) * yy);
        }
    }
    for (int c = 0; c < 3; ++c) {
        F s = basis[0] * coef(0, c);
        for (int k = 1; k < C; ++k) s = V::fma(basis[k], coef(k, c), s);
        rgb[c] = V::max(s + V::set1(0.5f), V::set1(0.0f));
    }
}

// Section 9 steps 1-3 for W Gaussians; writes lanes [0, lanes) of out.
static inline void project(const F x[3], const Mat3& rw, const F s[3], F opacity, const F rgb[3], const Cam& cam,
                           Splat* out, int lanes) {
    const float* R = cam.R;
    F p[3];
    for (int i = 0; i < 3; ++i)
        p[i] = V::fma(V::set1(R[3 * i]), x[0], V::fma(V::set1(R[3 * i + 1]), x[1],
                                                      V::fma(V::set1(R[3 * i + 2]), x[2], V::set1(cam.t[i]))));
    M valid = V::ge(p[2], V::set1(kNear));
    F zs = V::select(valid, p[2], V::set1(1.0f));
    F rz = V::set1(1.0f) / zs;
    const float tanx = 0.5f * cam.width / cam.fx, tany = 0.5f * cam.height / cam.fy;
    F txc = zs * V::min(V::set1((cam.width - cam.cx) / cam.fx + 0.3f * tanx),
                        V::max(V::set1(-(cam.cx / cam.fx + 0.3f * tanx)), p[0] * rz));
    F tyc = zs * V::min(V::set1((cam.height - cam.cy) / cam.fy + 0.3f * tany),
                        V::max(V::set1(-(cam.cy / cam.fy + 0.3f * tany)), p[1] * rz));
    F j00 = V::set1(cam.fx) * rz, j02 = -V::set1(cam.fx) * txc * rz * rz;
    F j11 = V::set1(cam.fy) * rz, j12 = -V::set1(cam.fy) * tyc * rz * rz;
    // M = Rc Rw S; T2 = J M; cov2d = T2 T2^T.
    F t0[3], t1[3];
    for (int c = 0; c < 3; ++c) {
        F m0 = V::fma(V::set1(R[0]), rw.m[c], V::fma(V::set1(R[1]), rw.m[3 + c], V::set1(R[2]) * rw.m[6 + c])) * s[c];
        F m1 = V::fma(V::set1(R[3]), rw.m[c], V::fma(V::set1(R[4]), rw.m[3 + c], V::set1(R[5]) * rw.m[6 + c])) * s[c];
        F m2 = V::fma(V::set1(R[6]), rw.m[c], V::fma(V::set1(R[7]), rw.m[3 + c], V::set1(R[8]) * rw.m[6 + c])) * s[c];
        t0[c] = V::fma(j00, m0, j02 * m2);
        t1[c] = V::fma(j11, m1, j12 * m2);
    }
    F c00 = dot3(t0[0], t0[1], t0[2], t0[0], t0[1], t0[2]);
    F c01 = dot3(t0[0], t0[1], t0[2], t1[0], t1[1], t1[2]);
    F c11 = dot3(t1[0], t1[1], t1[2], t1[0], t1[1], t1[2]);
    F det_raw = c00 * c11 - c01 * c01;
    c00 = c00 + V::set1(kEps2d);
    c11 = c11 + V::set1(kEps2d);
    F det = c00 * c11 - c01 * c01;
    valid = V::mand(valid, V::gt(det, V::set1(0.0f)));
    F dets = V::select(valid, det, V::set1(1.0f));
    F rdet = V::set1(1.0f) / dets;
    F op = opacity;
    if (cam.antialiased) op = op * V::sqrt(V::max(det_raw * rdet, V::set1(0.0f)));
    valid = V::mand(valid, V::ge(op, V::set1(kAlphaMin)));
    F mx = V::fma(V::set1(cam.fx), p[0] * rz, V::set1(cam.cx));
    F my = V::fma(V::set1(cam.fy), p[1] * rz, V::set1(cam.cy));
    // Pixels whose centres can pass alpha >= 1/255: inside mean +- sqrt(2 ln(255 o) diag S) (+0.01 px).
    F level = V::max(V::set1(2.0f) * vlog<V>(V::max(op, V::set1(kAlphaMin)) * V::set1(255.0f)), V::set1(0.0f));
    F hx = V::sqrt(level * c00) + V::set1(0.01f), hy = V::sqrt(level * c11) + V::set1(0.01f);
    F x0 = V::max(V::ceil(mx - hx - V::set1(0.5f)), V::set1(0.0f));
    F x1 = V::min(V::floor(mx + hx - V::set1(0.5f)) + V::set1(1.0f), V::set1(float(cam.width)));
    F y0 = V::max(V::ceil(my - hy - V::set1(0.5f)), V::set1(0.0f));
    F y1 = V::min(V::floor(my + hy - V::set1(0.5f)) + V::set1(1.0f), V::set1(float(cam.height)));
    valid = V::mand(valid, V::mand(V::lt(x0, x1), V::lt(y0, y1)));
    const F zero = V::set1(0.0f), l2e = V::set1(kLog2e);
    const F log2_op = vlog<V>(V::max(op, V::set1(kAlphaMin))) * l2e;
    alignas(64) float f[15][kMaxLanes];
    const F half_l2e = V::set1(0.5f * kLog2e);
    const F fields[15] = {mx, my, c11 * rdet * half_l2e, -c01 * rdet * l2e, c00 * rdet * half_l2e, log2_op, p[2],
                          rgb[0], rgb[1], rgb[2], V::select(valid, x0, zero), V::select(valid, x1, zero),
                          V::select(valid, y0, zero), V::select(valid, y1, zero),
                          V::max(log2_op + V::set1(7.994353436858858f), zero)};  // log2(255 o)
    for (int i = 0; i < 15; ++i) V::store(f[i], fields[i]);
    for (int l = 0; l < lanes; ++l) {
        Splat& o = out[l];
        o.t.mx = f[0][l], o.t.my = f[1][l], o.t.ha = f[2][l], o.t.cb = f[3][l], o.t.hc = f[4][l];
        o.t.log2_opacity = f[5][l], o.t.depth = f[6][l], o.t.r = f[7][l], o.t.g = f[8][l], o.t.b = f[9][l];
        o.t.level = f[14][l], o.t.id = 0;
        o.x0 = f[10][l], o.x1 = f[11][l], o.y0 = f[12][l], o.y1 = f[13][l];
    }
}

// ------------------------------------------------------------------------------------------------ deform

static void deform_project(const AvatarView& av, const float* blended, const float* A, const Cam& cam, Splat* out,
                           int n0, int n1) {
    const int DP = av.Dp, J = av.J;
    alignas(64) float wtail[32 * kMaxLanes];
    for (int g0 = n0; g0 < n1; g0 += W) {
        const int lanes = std::min(W, n1 - g0);
        // The blend left this block lane-interleaved ([d][lane]); tail lanes past n1 hold stale values that are
        // computed on but never written out.
        const float* buf = blended + size_t((g0 - n0) / W) * DP * W;
        const float* wbuf = av.lbs + g0;  // [J, n_total]: W consecutive Gaussians per joint
        size_t wstride = av.n_total;
        if (g0 + W > av.n_total) {  // the last block of the avatar: copy what exists
            for (int j = 0; j < J; ++j)
                for (int l = 0; l < W; ++l) wtail[j * W + l] = l < lanes ? av.lbs[size_t(j) * av.n_total + g0 + l] : 0.0f;
            wbuf = wtail, wstride = W;
        }
        // T = I + sum_j w_j (A_j - I), 3x4.
        F t[12];
        for (int e = 0; e < 12; ++e) t[e] = V::set1((e == 0 || e == 5 || e == 10) ? 1.0f : 0.0f);
        for (int j = 0; j < J; ++j) {
            const F w = V::load(wbuf + j * wstride);
            const float* a = A + j * 12;
            for (int e = 0; e < 12; ++e) {
                const float id = (e == 0 || e == 5 || e == 10) ? 1.0f : 0.0f;
                t[e] = V::fma(w, V::set1(a[e] - id), t[e]);
            }
        }
        F xr[3] = {V::load(buf), V::load(buf + W), V::load(buf + 2 * W)};
        F x[3];
        for (int i = 0; i < 3; ++i) x[i] = V::fma(t[4 * i], xr[0], V::fma(t[4 * i + 1], xr[1], V::fma(t[4 * i + 2], xr[2], t[4 * i + 3])));
        Mat3 rn;
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) rn.m[3 * i + j] = t[4 * i + j];
        rn = orthogonalize(rn);
        F qn[4], qg[4], qw[4];
        matrix_to_quat(rn, qn);
        for (int c = 0; c < 4; ++c) qg[c] = V::load(buf + (3 + c) * W);
        normalize4(qg);
        quat_mul(qn, qg, qw);
        normalize4(qw);
        Mat3 rw = quat_to_matrix(qw);
        F s[3];
        for (int c = 0; c < 3; ++c) s[c] = vexp<V>(V::load(buf + (7 + c) * W));
        F opacity = V::set1(1.0f) / (V::set1(1.0f) + vexp<V>(-V::load(buf + 10 * W)));
        // View direction in the Gaussian's rest frame: R_n^T normalise(x - centre).
        F d[3] = {x[0] - V::set1(cam.centre[0]), x[1] - V::set1(cam.centre[1]), x[2] - V::set1(cam.centre[2])};
        F inv = V::set1(1.0f) / V::max(V::sqrt(dot3(d[0], d[1], d[2], d[0], d[1], d[2])), V::set1(1e-12f));
        for (int i = 0; i < 3; ++i) d[i] = d[i] * inv;
        F dl[3];
        for (int j = 0; j < 3; ++j) dl[j] = dot3(rn.m[j], rn.m[3 + j], rn.m[6 + j], d[0], d[1], d[2]);
        F rgb[3];
        eval_sh(buf, av.C, dl[0], dl[1], dl[2], rgb);
        project(x, rw, s, opacity, rgb, cam, out + g0, lanes);
    }
}

static void project_posed(const PosedView& pv, int b, const Cam& cam, Splat* out, int n0, int n1) {
    alignas(64) float buf[14 * kMaxLanes];
    const size_t off = size_t(b) * pv.N;
    for (int g0 = n0; g0 < n1; g0 += W) {
        const int lanes = std::min(W, n1 - g0);
        for (int l = 0; l < W; ++l) {
            const size_t n = off + g0 + std::min(l, lanes - 1);
            for (int c = 0; c < 3; ++c) buf[c * W + l] = pv.means[n * 3 + c];
            for (int c = 0; c < 4; ++c) buf[(3 + c) * W + l] = pv.quats[n * 4 + c];
            for (int c = 0; c < 3; ++c) buf[(7 + c) * W + l] = pv.scales[n * 3 + c];
            buf[10 * W + l] = pv.opacities[n];
            for (int c = 0; c < 3; ++c) buf[(11 + c) * W + l] = pv.colors[n * 3 + c];
        }
        F x[3] = {V::load(buf), V::load(buf + W), V::load(buf + 2 * W)};
        F q[4];
        for (int c = 0; c < 4; ++c) q[c] = V::load(buf + (3 + c) * W);
        normalize4(q);
        Mat3 rw = quat_to_matrix(q);
        F s[3] = {V::load(buf + 7 * W), V::load(buf + 8 * W), V::load(buf + 9 * W)};
        F rgb[3] = {V::load(buf + 11 * W), V::load(buf + 12 * W), V::load(buf + 13 * W)};
        project(x, rw, s, V::load(buf + 10 * W), rgb, cam, out + g0, lanes);
    }
}

// ------------------------------------------------------------------------------------------------ raster

// Per-row pixel spans [lo, hi] of each splat's eligibility ellipse on the row's centre line (q <= level, plus
// 0.05 px; lo = 1e9, hi = -1e9 where empty): lo, hi are [rows][cpad] (with need given, rows with need[r] false
// are left as they are). The same arithmetic as composite_tile's.
static void tile_row_spans(const TileSplat* splats, int count, int cpad, int yb, int rows, const bool* need,
                           float* tmp, float* lo, float* hi) {
    float* my = tmp;
    float* xc0 = my + cpad;
    float* shear = xc0 + cpad;
    float* ia = shear + cpad;
    float* k2 = ia + cpad;
    float* k0 = k2 + cpad;
    for (int i = 0; i < cpad; ++i) {
        if (i < count) {
            const TileSplat& s = splats[i];
            my[i] = s.my, xc0[i] = s.mx - 0.5f, ia[i] = 0.5f / s.ha, shear[i] = 0.5f * s.cb / s.ha;
            k2[i] = s.cb * s.cb - 4.0f * s.ha * s.hc, k0[i] = 4.0f * s.ha * s.level;
        } else {
            my[i] = xc0[i] = shear[i] = k2[i] = 0.0f, ia[i] = 1.0f, k0[i] = -1.0f;
        }
    }
    const F big = V::set1(1e9f), zero = V::set1(0.0f);
    for (int r = 0; r < rows; ++r) {
        if (need != nullptr && !need[r]) continue;
        const F yc = V::set1(float(yb + r) + 0.5f);
        for (int c = 0; c < cpad; c += W) {
            const F dy = V::load(my + c) - yc;
            const F disc = V::fma(dy * dy, V::load(k2 + c), V::load(k0 + c));
            const F half = V::fma(V::sqrt(V::max(disc, zero)), V::load(ia + c), V::set1(0.05f));
            const F xc = V::fma(V::load(shear + c), dy, V::load(xc0 + c));
            const F l = V::ceil(xc - half);
            const F h = V::floor(xc + half);
            const M empty = V::mor(V::lt(disc, zero), V::gt(l, h));
            V::store(lo + size_t(r) * cpad + c, V::select(empty, big, l));
            V::store(hi + size_t(r) * cpad + c, V::select(empty, -big, h));
        }
    }
}

constexpr int kLazyChunk = 128;  // splats gathered and spanned at a time by the lazy schedule (a multiple of W)

// One 16x16 tile, in blocks of BR rows x BW columns, one vector each (BR x BW = W lanes). A block composites the
// Gaussians that reach it, in depth order, branch-free, with its transmittance, colour and depth in registers,
// until all its pixels have stopped; which Gaussians reach it comes from every row's exact pixel span of each
// Gaussian's eligibility ellipse (tile_row_spans), as one reach mask per block and W Gaussians, computed for a whole
// row of blocks at a time.
// The splats are taken in chunks: all at once (eager), or kLazyChunk at a time (lazy: a chunk is gathered and
// spanned, for the rows that still have live blocks, only when some pixel of the tile is still compositing; the
// tail behind a saturated tile costs nothing). Each block keeps its state between chunks, and every pixel's
// arithmetic and order are the same whatever the chunks and the block shape: the images are bit-identical, and
// the backward (splat_alpha) recomputes the same alpha row by row.
// Train: also write each pixel's final transmittance and last contributor (1-based; 0: none) for the backward.
template <bool Train, int BR, int BW, bool Stop8 = false>
static void composite_tile(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty, const Cam& cam,
                           const float* background, const TileOut& o, bool lazy) {
    static_assert(BR * BW == W, "a block is one vector");
    constexpr int kMaxBlocks = kTile * kTile / W;
    const int xb = tx * kTile, yb = ty * kTile;
    const int xe = std::min(xb + kTile, cam.width), ye = std::min(yb + kTile, cam.height);
    const int rows = ye - yb;
    const int bcols = (xe - xb + BW - 1) / BW, nblocks = (rows + BR - 1) / BR * bcols;
    const int cpad = (count + W - 1) / W * W;
    const int chunk = lazy ? std::min(cpad, kLazyChunk) : cpad;
    static thread_local std::vector<float> scratch_tls;
    static thread_local std::vector<TileSplat> gathered_tls;
    static thread_local std::vector<uint32_t> reach_tls;  // per block, a reach mask per W splats of a chunk
    std::vector<uint32_t>& reach_bits = reach_tls;
    const int groups = chunk / W;
    if (reach_bits.size() < size_t(kMaxBlocks) * groups) reach_bits.resize(size_t(kMaxBlocks) * groups);
    std::vector<float>& scratch = scratch_tls;
    if (scratch.size() < size_t(chunk) * (6 + 2 * kTile)) scratch.resize(size_t(chunk) * (6 + 2 * kTile));
    if (pos != nullptr && gathered_tls.size() < size_t(chunk)) gathered_tls.resize(chunk);
    float* lo = scratch.data() + size_t(6) * chunk;
    float* hi = lo + size_t(kTile) * chunk;
    alignas(64) float lane_col[kMaxLanes], lane_row[kMaxLanes];
    for (int l = 0; l < W; ++l) lane_col[l] = float(l % BW), lane_row[l] = float(l / BW);
    const F col = V::load(lane_col), row = V::load(lane_row);
    const F one = V::set1(1.0f), zero = V::set1(0.0f);
    const F amax = V::set1(kAlphaMax), amin = V::set1(kAlphaMin), tstop = V::set1(kTStop);
    const F tstop8 = V::set1(kTStop8);
    // Per block: T, R, G, B, depth, last contributor, live (1 or 0) per lane.
    alignas(64) float state[kMaxBlocks][7][W];
    bool block_live[kMaxBlocks];
    int alive = 0;
    for (int bi = 0; bi < nblocks; ++bi) {
        const int r0 = bi / bcols * BR, x0 = xb + bi % bcols * BW;
        const M live = V::mand(V::lt(V::set1(float(x0) + 0.5f) + col, V::set1(float(xe))),
                               V::lt(row, V::set1(float(rows - r0))));
        V::store(state[bi][0], one);
        for (int f = 1; f < 6; ++f) V::store(state[bi][f], zero);
        V::store(state[bi][6], V::select(live, one, zero));
        block_live[bi] = V::any(live);
        alive += block_live[bi];
    }
    for (int c0 = 0; c0 < cpad && alive > 0; c0 += chunk) {
        const int cn = std::min(chunk, cpad - c0), real = std::min(cn, count - c0);
        const TileSplat* splats = sorted + c0;
        if (pos != nullptr) {
            TileSplat* g = gathered_tls.data();
            constexpr int kAhead = 16;  // the records lie far apart in depth order: prefetch both of a record's lines
            for (int j = 0; j < real; ++j) {
                if (j + kAhead < real) {
                    const char* ahead = reinterpret_cast<const char*>(sorted + pos[c0 + j + kAhead]);
                    __builtin_prefetch(ahead), __builtin_prefetch(ahead + sizeof(TileSplat) - 1);
                }
                g[j] = sorted[pos[c0 + j]];
            }
            splats = g;
        }
        bool need[kTile] = {};
        for (int bi = 0; bi < nblocks; ++bi)
            if (block_live[bi])
                for (int r = bi / bcols * BR; r < std::min(bi / bcols * BR + BR, rows); ++r) need[r] = true;
        tile_row_spans(splats, real, cn, yb, rows, need, scratch.data(), lo, hi);
        // Which Gaussians may reach each live block: those whose span on some row of the block's row of blocks
        // (their union's hull: lowest lo, highest hi) meets the block's columns. A superset of the Gaussians
        // whose eligibility reaches one of the block's pixels (the others then take alpha 0 there and change
        // nothing), computed once per row of blocks for all its blocks.
        for (int br = 0; br * BR < rows; ++br) {
            const int r0 = br * BR, nr = std::min(BR, rows - r0);
            if (!need[r0]) continue;
            for (int c = 0; c < cn; c += W) {
                F l = V::load(lo + size_t(r0) * cn + c), h = V::load(hi + size_t(r0) * cn + c);
                for (int r = 1; r < nr; ++r) {
                    l = V::min(l, V::load(lo + size_t(r0 + r) * cn + c));
                    h = V::max(h, V::load(hi + size_t(r0 + r) * cn + c));
                }
                for (int bc = 0; bc < bcols; ++bc) {
                    const float x0 = float(xb + bc * BW);
                    reach_bits[size_t(br * bcols + bc) * groups + c / W] =
                        V::bits(V::mand(V::le(l, V::set1(x0 + float(BW - 1))), V::ge(h, V::set1(x0))));
                }
            }
        }
        for (int bi = 0; bi < nblocks; ++bi) {
            if (!block_live[bi]) continue;
            const int r0 = bi / bcols * BR, x0 = xb + bi % bcols * BW;
            const F px = V::set1(float(x0) + 0.5f) + col;
            const F yc = V::set1(float(yb + r0) + 0.5f) + row;  // each lane's row centre
            F T = V::load(state[bi][0]), Cr = V::load(state[bi][1]), Cg = V::load(state[bi][2]);
            F Cb = V::load(state[bi][3]), D = V::load(state[bi][4]), L = V::load(state[bi][5]);
            M live = V::gt(V::load(state[bi][6]), zero);
            const uint32_t* block_reach = reach_bits.data() + size_t(bi) * groups;
            for (int c = 0; c < cn && V::any(live); c += W) {
                unsigned reach = block_reach[c / W];
                while (reach) {
                    const int i = c + __builtin_ctz(reach);
                    const TileSplat& s = splats[i];
                    reach &= reach - 1;
                    const F dx = V::set1(s.mx) - px;
                    const F dy = V::set1(s.my) - yc;
                    const F cbdy = V::set1(s.cb) * dy, hcdy2 = V::set1(s.hc) * dy * dy;
                    const F q = V::fma(dx, V::fma(V::set1(s.ha), dx, cbdy), hcdy2);
                    // Lanes that skip this Gaussian (not ok) keep T: T (1 - 0) = T exactly. Kept: composited,
                    // its T above the exact rule's stop; the others add nothing (w = 0) and keep their T.
                    const F a = V::min(amax, vexp2<V>(V::set1(s.log2_opacity) - q));
                    const M ok = V::ge_and(V::ge_and(live, q, zero), a, amin);
                    const F nt = T * V::sub_if(ok, one, a);
                    const M kept = V::gt_and(ok, nt, tstop);
                    const F w = V::mul_if(kept, a, T);
                    Cr = V::fma(w, V::set1(s.r), Cr);
                    Cg = V::fma(w, V::set1(s.g), Cg);
                    Cb = V::fma(w, V::set1(s.b), Cb);
                    if constexpr (!Stop8) D = V::fma(w, V::set1(s.depth), D);  // 8-bit output has no depth
                    T = V::select(kept, nt, T);
                    if constexpr (Train) L = V::select(kept, V::set1(float(c0 + i + 1)), L);
                    if constexpr (Stop8)  // this splat composited and T below kTStop8, or the exact stop (T < kTStop)
                        live = V::mandnot(V::le_and(ok, nt, tstop8), live);
                    else  // the exact stop: ok, not kept
                        live = V::mandnot(V::mandnot(kept, ok), live);
                }
            }
            V::store(state[bi][0], T), V::store(state[bi][1], Cr), V::store(state[bi][2], Cg);
            V::store(state[bi][3], Cb), V::store(state[bi][4], D), V::store(state[bi][5], L);
            V::store(state[bi][6], V::select(live, one, zero));
            if (!V::any(live)) block_live[bi] = false, --alive;
        }
    }
    // The block's pixels, computed a vector at a time: colour over the background, alpha, depth and, for RGBA8,
    // x * 255 rounded to float, then + 0.5 (as to_rgba8: two roundings, never one FMA), truncated when stored.
    const F bg[3] = {V::set1(background[0]), V::set1(background[1]), V::set1(background[2])};
    const F k255 = V::set1(255.0f), half = V::set1(0.5f);
    float* const rgb = o.rgb;
    float* const alpha = o.alpha;
    float* const depth = o.depth;
    uint8_t* const rgba8 = o.rgba8;
    static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "RGBA8 words are stored little-endian");
    for (int bi = 0; bi < nblocks; ++bi) {
        const int r0 = bi / bcols * BR, x0 = xb + bi % bcols * BW;
        const F T = V::load(state[bi][0]);
        alignas(64) float px[8][W];
        for (int c = 0; c < 3; ++c) V::store(px[c], V::fma(T, bg[c], V::load(state[bi][1 + c])));
        V::store(px[3], one - T);
        if (rgba8 != nullptr)
            for (int c = 0; c < 4; ++c)
                V::store(px[4 + c], V::opaque(V::min(V::max(V::load(px[c]), zero), one) * k255) + half);
        // Row by row, each output in its own loop (the pointers in locals: the byte stores could alias them),
        // an RGBA8 row packed into 32-bit words and copied at once.
        const int ncol = std::min(BW, xe - x0), nrow = std::min(BR, rows - r0);
        for (int r = 0; r < nrow; ++r) {
            const size_t p0 = size_t(yb + r0 + r) * cam.width + x0;
            const int l0 = r * BW;
            if (rgba8 != nullptr) {
                uint32_t packed[BW];
                for (int x = 0; x < BW; ++x)
                    packed[x] = uint32_t(px[4][l0 + x]) | uint32_t(px[5][l0 + x]) << 8 |
                                uint32_t(px[6][l0 + x]) << 16 | uint32_t(px[7][l0 + x]) << 24;
                std::memcpy(rgba8 + p0 * 4, packed, size_t(ncol) * 4);
            }
            if (rgb != nullptr)
                for (int x = 0; x < ncol; ++x)
                    for (int c = 0; c < 3; ++c) rgb[(p0 + x) * 3 + c] = px[c][l0 + x];
            if (alpha != nullptr)
                for (int x = 0; x < ncol; ++x) alpha[p0 + x] = px[3][l0 + x];
            if (depth != nullptr)
                for (int x = 0; x < ncol; ++x) depth[p0 + x] = state[bi][4][l0 + x];
            if constexpr (Train)
                for (int x = 0; x < ncol; ++x)
                    o.T[p0 + x] = state[bi][0][l0 + x], o.last[p0 + x] = uint32_t(state[bi][5][l0 + x]);
        }
    }
}

// 8 x 2 pixels with 16 lanes, 8 x 1 with 8, 1 x 1 with one; square: 4 x 4, 4 x 2, 1 x 1.
constexpr int kWideBW = W < 8 ? W : 8;
constexpr int kSquareBW = W >= 8 ? 4 : W;

// One block shape, the exact rule or the 8-bit stop.
template <int BR, int BW>
static void composite_shape(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty, const Cam& cam,
                            const float* background, const TileOut& out, bool lazy, bool stop8) {
    if (stop8)
        composite_tile<false, BR, BW, true>(sorted, pos, count, tx, ty, cam, background, out, lazy);
    else
        composite_tile<false, BR, BW>(sorted, pos, count, tx, ty, cam, background, out, lazy);
}

static void raster_tile(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty, const Cam& cam,
                        const float* background, const TileOut& out, unsigned flags) {
    const bool lazy = (flags & kLazyTiles) != 0;
    const bool stop8 = (flags & kEightBitStop) != 0 && out.rgba8 != nullptr && out.rgb == nullptr &&
                       out.alpha == nullptr && out.depth == nullptr;
    if (flags & kSquareBlocks)
        composite_shape<W / kSquareBW, kSquareBW>(sorted, pos, count, tx, ty, cam, background, out, lazy, stop8);
    else
        composite_shape<W / kWideBW, kWideBW>(sorted, pos, count, tx, ty, cam, background, out, lazy, stop8);
}

// The training forward: the same image, plus T and the last contributor per pixel (see backward.inl).
static void raster_tile_train(const TileSplat* sorted, const uint32_t* pos, int count, int tx, int ty,
                              const Cam& cam, const float* background, float* rgb, float* alpha, float* depth,
                              float* Tout, uint32_t* last_out) {
    TileOut o;
    o.rgb = rgb, o.alpha = alpha, o.depth = depth, o.T = Tout, o.last = last_out;
    composite_tile<true, W / kWideBW, kWideBW>(sorted, pos, count, tx, ty, cam, background, o, false);
}

const Kernels& kernels() {
    static const Kernels k{V::name, &blend, &deform_project, &project_posed, &raster_tile};
    return k;
}

}  // namespace BS_NS
}  // namespace bs
