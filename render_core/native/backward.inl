// The backward kernels (see backward.hpp), written once over the SIMD wrapper V and compiled once per
// instruction set: kernels_scalar.cpp, kernels_avx2.cpp and kernels_avx512.cpp include this file after
// kernels.inl (whose V, F, M and W it uses).
//
// The training forward is raster_tile_train (kernels.inl: the same compositing loop as raster_tile, so the same
// image bit for bit, also recording each pixel's final transmittance and last contributor). The backward
// recomputes every alpha of the tile with that same arithmetic, so it takes the forward's decisions (1/255 skip,
// 0.999 clamp, transmittance stop) for every pair.

#include "backward.hpp"

namespace bs {
namespace BS_NS {

// Alpha of splat s at W pixel centres px on a row at offset dy = my - yc: q (base-2 exponent) and the clamped
// alpha, exactly as raster_tile computes them; e is the unclamped value.
static inline void splat_alpha(const TileSplat& s, F px, float dy, F& dx, F& q, F& e, F& a) {
    dx = V::set1(s.mx) - px;
    q = V::fma(dx, V::fma(V::set1(s.ha), dx, V::set1(s.cb * dy)), V::set1(s.hc * dy * dy));
    e = vexp2<V>(V::set1(s.log2_opacity) - q);
    a = V::min(V::set1(kAlphaMax), e);
}

// ------------------------------------------------------------------------------------------------ backward

// Splat-major, back to front: per-pixel state (T after the splat, the loss gradient carried by everything
// behind it, the last-contributor count and dL/drgb) lives in small tile arrays; each splat visits the segments
// its row spans reach, and its moments accumulate in registers (one horizontal sum per moment per tile).
//
// Per pixel, with T_i the transmittance in front of contributor i, w_i = a_i T_i and
// S_i = sum_{j > i} w_j (c_j . g) + T_final (bg . g - dL/dalpha):
//   dL/da_i = T_i (c_i . g) - S_i / (1 - a_i),   T_i = T_{i+1} / (1 - a_i),   S_{i-1} = S_i + w_i (c_i . g).
static void backward_tile(const Splat* frame, const uint32_t* ids, int count, int tx, int ty, const Cam& cam,
                          const float* Tfin, const uint32_t* last, const float* grad_rgb, const float* grad_alpha,
                          const float* background, const uint32_t* goff, float* moments) {
    constexpr int NS = kTile / W;
    constexpr int P = kTile * kTile;
    const int xb = tx * kTile, yb = ty * kTile;
    const int xe = std::min(xb + kTile, cam.width), ye = std::min(yb + kTile, cam.height);
    const int rows = ye - yb;
    const int cpad = (count + W - 1) / W * W;
    static thread_local std::vector<float> scratch_tls;
    static thread_local std::vector<TileSplat> local_tls;
    std::vector<float>& scratch = scratch_tls;
    std::vector<TileSplat>& local = local_tls;
    const size_t need = size_t(cpad) * (6 + 2 * kTile) + 6 * P;
    if (scratch.size() < need) scratch.resize(need);
    if (local.size() < size_t(count)) local.resize(count);
    for (int i = 0; i < count; ++i) local[i] = frame[ids[i]].t;
    float* lo = scratch.data() + size_t(6) * cpad;
    float* hi = lo + size_t(kTile) * cpad;
    float* sT = hi + size_t(kTile) * cpad;  // [P] each: T, S, last, dL/dr, dL/dg, dL/db (row stride kTile)
    float* sS = sT + P;
    float* sL = sS + P;
    float* sR = sL + P;
    float* sG = sR + P;
    float* sB = sG + P;
    tile_row_spans(local.data(), count, cpad, yb, rows, nullptr, scratch.data(), lo, hi);

    uint32_t maxlast = 0;
    for (int r = 0; r < kTile; ++r) {
        for (int i = 0; i < kTile; ++i) {
            const int q = r * kTile + i, x = xb + i, y = yb + r;
            if (r < rows && x < xe) {
                const size_t p = size_t(y) * cam.width + x;
                const float gr = grad_rgb[3 * p], gg = grad_rgb[3 * p + 1], gb = grad_rgb[3 * p + 2];
                sT[q] = Tfin[p];
                sS[q] = Tfin[p] * (gr * background[0] + gg * background[1] + gb * background[2] - grad_alpha[p]);
                sL[q] = float(last[p]);
                sR[q] = gr, sG[q] = gg, sB[q] = gb;
                maxlast = std::max(maxlast, last[p]);
            } else {
                sT[q] = 1.0f, sS[q] = sL[q] = sR[q] = sG[q] = sB[q] = 0.0f;
            }
        }
    }

    auto slot_of = [&](int i) -> float* {
        const uint32_t g = ids[i];
        const TileRect r = tile_rect(frame[g]);
        return moments + size_t(kMoments) * (goff[g] + uint32_t((ty - r.y0) * (r.x1 - r.x0 + 1) + (tx - r.x0)));
    };
    for (int i = int(maxlast); i < count; ++i) std::fill_n(slot_of(i), kMoments, 0.0f);

    const F iota = V::iota(), one = V::set1(1.0f), zero = V::set1(0.0f);
    const F amax = V::set1(kAlphaMax), amin = V::set1(kAlphaMin);
    for (int i = int(maxlast) - 1; i >= 0; --i) {
        const TileSplat& s = local[i];
        const F fi = V::set1(float(i));
        F acc[kMoments];
        for (int m = 0; m < kMoments; ++m) acc[m] = zero;
        bool touched = false;
        for (int r = 0; r < rows; ++r) {
            const float slo = lo[size_t(r) * cpad + i], shi = hi[size_t(r) * cpad + i];
            if (slo > shi) continue;
            const float yc = float(yb + r) + 0.5f, dy = s.my - yc;
            const F vdy = V::set1(dy);
            for (int sg = 0; sg < NS; ++sg) {
                const int x0 = xb + sg * W;
                if (!(slo <= float(x0 + W - 1) && shi >= float(x0))) continue;
                const int q0 = r * kTile + sg * W;
                const F px = V::set1(float(x0) + 0.5f) + iota;
                F dx, q, e, a;
                splat_alpha(s, px, dy, dx, q, e, a);
                const M ok = V::mand(V::lt(fi, V::load(sL + q0)), V::mand(V::ge(q, zero), V::ge(a, amin)));
                if (!V::any(ok)) continue;
                touched = true;
                const F gr = V::load(sR + q0), gg = V::load(sG + q0), gb = V::load(sB + q0);
                const F S = V::load(sS + q0);
                const F rom = one / (one - a);
                const F Ti = V::load(sT + q0) * rom;
                const F cg = V::fma(V::set1(s.r), gr, V::fma(V::set1(s.g), gg, V::set1(s.b) * gb));
                const F w = V::select(ok, a * Ti, zero);
                const F dlda = (Ti * cg - S * rom);
                const F v = V::select(V::mand(ok, V::le(e, amax)), dlda * a, zero);
                V::store(sS + q0, V::fma(w, cg, S));
                V::store(sT + q0, V::select(ok, Ti, V::load(sT + q0)));
                const F vdx = v * dx;
                acc[0] = acc[0] + v;
                acc[1] = acc[1] + vdx;
                acc[2] = V::fma(vdx, dx, acc[2]);
                acc[3] = V::fma(v, vdy, acc[3]);
                acc[4] = V::fma(vdx, vdy, acc[4]);
                acc[5] = V::fma(v * vdy, vdy, acc[5]);
                acc[6] = V::fma(w, gr, acc[6]);
                acc[7] = V::fma(w, gg, acc[7]);
                acc[8] = V::fma(w, gb, acc[8]);
            }
        }
        float* out = slot_of(i);
        for (int m = 0; m < kMoments; ++m) out[m] = touched ? V::hsum(acc[m]) : 0.0f;
    }
}

// ------------------------------------------------------------------------------------------------ projection

// Section 9 steps 1-2 and 7 backwards for Gaussians [n0, n1) of frame b, W at a time (float32): the moments of
// each one's pairs summed in pair order (in double), then the chain rule through the compositing opacity and
// conic, the inverse of the blurred 2D covariance (and the antialiasing compensation), the EWA covariance
// J Rc Rw S S Rw^T Rc^T J^T with the clamped Jacobian, the quaternion's rotation matrix and normalisation, and
// the perspective projection of the mean.
static void project_backward(const PosedView& pv, int b, const Cam& cam, const Splat* splats, const uint32_t* goff,
                             const float* moments, const PosedGrads& g, int n0, int n1) {
    const float* R = cam.R;
    const F fx = V::set1(cam.fx), fy = V::set1(cam.fy);
    const float tanx = 0.5f * cam.width / cam.fx, tany = 0.5f * cam.height / cam.fy;
    const F lxp = V::set1((cam.width - cam.cx) / cam.fx + 0.3f * tanx), lxn = V::set1(-(cam.cx / cam.fx + 0.3f * tanx));
    const F lyp = V::set1((cam.height - cam.cy) / cam.fy + 0.3f * tany), lyn = V::set1(-(cam.cy / cam.fy + 0.3f * tany));
    const F zero = V::set1(0.0f), one = V::set1(1.0f), two = V::set1(2.0f), eps = V::set1(kEps2d);
    // Inputs per lane: mean 3, quaternion 4, scale 3, opacity 1, moments 9; outputs: mean 3, quat 4, scale 3,
    // opacity 1, colour 3.
    alignas(64) float in[20][kMaxLanes];
    alignas(64) float out[14][kMaxLanes];
    bool active[kMaxLanes];
    for (int g0 = n0; g0 < n1; g0 += W) {
        const int lanes = std::min(W, n1 - g0);
        int first = -1;
        for (int l = 0; l < W; ++l) {
            const int n = g0 + l;
            double mom[kMoments] = {};
            bool any = false;
            if (l < lanes && splats[n].x0 < splats[n].x1) {
                const float* m = moments + size_t(kMoments) * goff[n];
                const uint32_t k = goff[n + 1] - goff[n];
                for (uint32_t j = 0; j < k; ++j)
                    for (int e = 0; e < kMoments; ++e) mom[e] += m[size_t(j) * kMoments + e];
                for (int e = 0; e < kMoments; ++e) any |= mom[e] != 0.0;
            }
            // Culled, or no pixel took it: no gradient (and no arithmetic on culled values: the lane computes on
            // an active lane's inputs with zero moments, and is written as zeros).
            active[l] = any;
            if (any && first < 0) first = l;
            const size_t gi = size_t(b) * pv.N + (any ? n : g0 + std::max(first, 0));
            for (int c = 0; c < 3; ++c) in[c][l] = pv.means[gi * 3 + c];
            for (int c = 0; c < 4; ++c) in[3 + c][l] = pv.quats[gi * 4 + c];
            for (int c = 0; c < 3; ++c) in[7 + c][l] = pv.scales[gi * 3 + c];
            in[10][l] = pv.opacities[gi];
            for (int e = 0; e < kMoments; ++e) in[11 + e][l] = float(mom[e]);
        }
        if (first >= 0) {
            for (int l = 0; l < first; ++l) {  // lanes before the first active one: its inputs too
                const size_t gi = size_t(b) * pv.N + g0 + first;
                for (int c = 0; c < 3; ++c) in[c][l] = pv.means[gi * 3 + c];
                for (int c = 0; c < 4; ++c) in[3 + c][l] = pv.quats[gi * 4 + c];
                for (int c = 0; c < 3; ++c) in[7 + c][l] = pv.scales[gi * 3 + c];
                in[10][l] = pv.opacities[gi];
            }
            const F x[3] = {V::load(in[0]), V::load(in[1]), V::load(in[2])};
            const F q[4] = {V::load(in[3]), V::load(in[4]), V::load(in[5]), V::load(in[6])};
            const F s[3] = {V::load(in[7]), V::load(in[8]), V::load(in[9])};
            const F o = V::load(in[10]);
            F mom[kMoments];
            for (int e = 0; e < kMoments; ++e) mom[e] = V::load(in[11 + e]);

            // Forward again (as project()).
            F p[3];
            for (int i = 0; i < 3; ++i)
                p[i] = V::fma(V::set1(R[3 * i]), x[0], V::fma(V::set1(R[3 * i + 1]), x[1],
                                                              V::fma(V::set1(R[3 * i + 2]), x[2], V::set1(cam.t[i]))));
            const F rz = one / p[2], rz2 = rz * rz;
            const F u = p[0] * rz, w = p[1] * rz;
            const F uc = V::min(lxp, V::max(lxn, u)), wc = V::min(lyp, V::max(lyn, w));
            const M xin = V::mand(V::ge(u, lxn), V::le(u, lxp)), yin = V::mand(V::ge(w, lyn), V::le(w, lyp));
            const F txc = p[2] * uc, tyc = p[2] * wc;
            const F j00 = fx * rz, j02 = -(fx * txc * rz2), j11 = fy * rz, j12 = -(fy * tyc * rz2);
            const F qnorm = V::sqrt(V::fma(q[0], q[0], V::fma(q[1], q[1], V::fma(q[2], q[2], q[3] * q[3]))));
            const F qden = V::max(qnorm, V::set1(1e-12f));
            const F qw = q[0] / qden, qx = q[1] / qden, qy = q[2] / qden, qz = q[3] / qden;
            const F rw[9] = {one - two * (qy * qy + qz * qz), two * (qx * qy - qw * qz), two * (qx * qz + qw * qy),
                             two * (qx * qy + qw * qz), one - two * (qx * qx + qz * qz), two * (qy * qz - qw * qx),
                             two * (qx * qz - qw * qy), two * (qy * qz + qw * qx), one - two * (qx * qx + qy * qy)};
            F P[9];  // Rc Rw diag(s)
            for (int i = 0; i < 3; ++i)
                for (int c = 0; c < 3; ++c)
                    P[3 * i + c] = V::fma(V::set1(R[3 * i]), rw[c],
                                          V::fma(V::set1(R[3 * i + 1]), rw[3 + c], V::set1(R[3 * i + 2]) * rw[6 + c])) *
                                   s[c];
            F t0[3], t1[3];
            for (int c = 0; c < 3; ++c) t0[c] = V::fma(j00, P[c], j02 * P[6 + c]), t1[c] = V::fma(j11, P[3 + c], j12 * P[6 + c]);
            const F c00r = dot3(t0[0], t0[1], t0[2], t0[0], t0[1], t0[2]);
            const F c01 = dot3(t0[0], t0[1], t0[2], t1[0], t1[1], t1[2]);
            const F c11r = dot3(t1[0], t1[1], t1[2], t1[0], t1[1], t1[2]);
            const F c00 = c00r + eps, c11 = c11r + eps;
            const F det = c00 * c11 - c01 * c01, idet = one / det, idet2 = idet * idet;
            const F A = c11 * idet, Bc = -(c01 * idet), C = c00 * idet;
            F comp = one;
            if (cam.antialiased) comp = V::sqrt(V::max((c00r * c11r - c01 * c01) * idet, zero));
            const F opc = o * comp;

            // Moments -> 2D mean, conic and compositing opacity (sigma = 0.5 (A dx^2 + C dy^2) + B dx dy,
            // dL/dsigma = -v).
            const F half = V::set1(0.5f);
            const F gA = -(half * mom[2]), gB = -mom[4], gC = -(half * mom[5]);
            const F gmx = -V::fma(A, mom[1], Bc * mom[3]), gmy = -V::fma(Bc, mom[1], C * mom[3]);
            const F gopc = mom[0] / opc;
            const F go = gopc * comp;
            // Conic = inverse of the blurred covariance.
            F g00 = gA * (-(c11 * c11 * idet2)) + gB * (c01 * c11 * idet2) + gC * (idet - c00 * c11 * idet2);
            F g11 = gA * (idet - c11 * c00 * idet2) + gB * (c01 * c00 * idet2) + gC * (-(c00 * c00 * idet2));
            F g01 = gA * (two * c11 * c01 * idet2) + gB * (-idet - two * c01 * c01 * idet2) +
                    gC * (two * c00 * c01 * idet2);
            if (cam.antialiased) {
                // comp = sqrt(r), r = det_raw / det: dr/dc00r = e (c11r c11 + c01^2) / det^2 (and symmetric),
                // dr/dc01 = -2 e c01 (c00r + c11r + e) / det^2 with e = 0.3.
                const F gr = V::select(V::gt(comp, zero), gopc * o * half / comp, zero) * eps * idet2;
                g00 = V::fma(gr, V::fma(c11r, c11, c01 * c01), g00);
                g11 = V::fma(gr, V::fma(c00r, c00, c01 * c01), g11);
                g01 = V::fma(gr, -(two * c01 * (c00r + c11r + eps)), g01);
            }
            // cov2d = T2 T2^T with rows t0, t1 of T2 = J P.
            F gt0[3], gt1[3];
            for (int c = 0; c < 3; ++c) {
                gt0[c] = V::fma(two * g00, t0[c], g01 * t1[c]);
                gt1[c] = V::fma(g01, t0[c], two * g11 * t1[c]);
            }
            const F gj00 = dot3(gt0[0], gt0[1], gt0[2], P[0], P[1], P[2]);
            const F gj02 = dot3(gt0[0], gt0[1], gt0[2], P[6], P[7], P[8]);
            const F gj11 = dot3(gt1[0], gt1[1], gt1[2], P[3], P[4], P[5]);
            const F gj12 = dot3(gt1[0], gt1[1], gt1[2], P[6], P[7], P[8]);
            F gP[9];
            for (int c = 0; c < 3; ++c) gP[c] = j00 * gt0[c], gP[3 + c] = j11 * gt1[c], gP[6 + c] = V::fma(j02, gt0[c], j12 * gt1[c]);
            // P = Rc Q, Q = Rw diag(s).
            F gR[9], gs[3] = {zero, zero, zero};
            for (int k = 0; k < 3; ++k)
                for (int c = 0; c < 3; ++c) {
                    const F gQ = V::fma(V::set1(R[k]), gP[c], V::fma(V::set1(R[3 + k]), gP[3 + c], V::set1(R[6 + k]) * gP[6 + c]));
                    gR[3 * k + c] = gQ * s[c];
                    gs[c] = V::fma(gQ, rw[3 * k + c], gs[c]);
                }
            // Rotation matrix of the unit quaternion (w, x, y, z).
            F gn[4];
            gn[0] = two * (qz * (gR[3] - gR[1]) + qy * (gR[2] - gR[6]) + qx * (gR[7] - gR[5]));
            gn[1] = two * (qy * (gR[1] + gR[3]) + qz * (gR[2] + gR[6]) + qw * (gR[7] - gR[5]) -
                           two * qx * (gR[4] + gR[8]));
            gn[2] = two * (qx * (gR[1] + gR[3]) + qw * (gR[2] - gR[6]) + qz * (gR[5] + gR[7]) -
                           two * qy * (gR[0] + gR[8]));
            gn[3] = two * (qw * (gR[3] - gR[1]) + qx * (gR[2] + gR[6]) + qy * (gR[5] + gR[7]) -
                           two * qz * (gR[0] + gR[4]));
            // Normalisation q / max(|q|, 1e-12): the tangential part over |q| (all of it below 1e-12).
            const F d = V::fma(qw, gn[0], V::fma(qx, gn[1], V::fma(qy, gn[2], qz * gn[3])));
            const F dn = V::select(V::gt(qnorm, V::set1(1e-12f)), d, zero);
            const F qn[4] = {qw, qx, qy, qz};
            F gq[4];
            for (int c = 0; c < 4; ++c) gq[c] = (gn[c] - qn[c] * dn) / qden;
            // Camera-space mean: 2D mean, J (clamped view direction) and depth.
            F gp0 = gmx * fx * rz, gp1 = gmy * fy * rz;
            F gz = -(V::fma(gmx * fx, p[0], gmy * fy * p[1]) * rz2);
            gz = gz - V::fma(gj00, fx, gj11 * fy) * rz2;
            const F gtx = -(gj02 * fx * rz2), gty = -(gj12 * fy * rz2);
            gz = V::fma(two * V::fma(gj02 * fx, txc, gj12 * fy * tyc), rz2 * rz, gz);
            gp0 = gp0 + V::select(xin, gtx, zero);
            gp1 = gp1 + V::select(yin, gty, zero);
            gz = gz + V::select(xin, zero, gtx * uc) + V::select(yin, zero, gty * wc);
            for (int c = 0; c < 3; ++c)
                V::store(out[c], V::fma(V::set1(R[c]), gp0, V::fma(V::set1(R[3 + c]), gp1, V::set1(R[6 + c]) * gz)));
            for (int c = 0; c < 4; ++c) V::store(out[3 + c], gq[c]);
            for (int c = 0; c < 3; ++c) V::store(out[7 + c], gs[c]);
            V::store(out[10], go);
            for (int c = 0; c < 3; ++c) V::store(out[11 + c], mom[6 + c]);
        }
        for (int l = 0; l < lanes; ++l) {
            const size_t gi = size_t(b) * pv.N + g0 + l;
            const bool a = active[l];
            for (int c = 0; c < 3; ++c) g.means[gi * 3 + c] = a ? out[c][l] : 0.0f;
            for (int c = 0; c < 4; ++c) g.quats[gi * 4 + c] = a ? out[3 + c][l] : 0.0f;
            for (int c = 0; c < 3; ++c) g.scales[gi * 3 + c] = a ? out[7 + c][l] : 0.0f;
            g.opacities[gi] = a ? out[10][l] : 0.0f;
            for (int c = 0; c < 3; ++c) g.colors[gi * 3 + c] = a ? out[11 + c][l] : 0.0f;
        }
    }
}

const BackwardKernels& backward_kernels() {
    static const BackwardKernels k{V::name, &raster_tile_train, &backward_tile, &project_backward};
    return k;
}

}  // namespace BS_NS
}  // namespace bs
