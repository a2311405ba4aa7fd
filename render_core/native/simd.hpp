// Thin SIMD wrappers: one kernel source (kernels.inl) is compiled once per instruction set with V = Scalar,
// Avx2 or Avx512. Each wrapper provides a float vector F (W lanes), a lane mask M, and the handful of operations
// the kernels need. exp/log are Cephes-style polynomial approximations (about 1 ulp) in the vector paths and
// the C library's in the scalar path.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#if defined(BS_ISA_AVX2) || defined(BS_ISA_AVX512)
#include <immintrin.h>
#endif

namespace bs {

inline float half_to_float(uint16_t h) {
    const uint32_t sign = uint32_t(h & 0x8000u) << 16;
    uint32_t exp = (h >> 10) & 0x1fu;
    uint32_t mant = h & 0x3ffu;
    uint32_t bits;
    if (exp == 0) {
        if (mant == 0) {
            bits = sign;
        } else {  // subnormal half: normalise
            exp = 127 - 15 + 1;
            while ((mant & 0x400u) == 0) {
                mant <<= 1;
                --exp;
            }
            mant &= 0x3ffu;
            bits = sign | (exp << 23) | (mant << 13);
        }
    } else if (exp == 0x1f) {
        bits = sign | 0x7f800000u | (mant << 13);
    } else {
        bits = sign | ((exp - 15 + 127) << 23) | (mant << 13);
    }
    float f;
    std::memcpy(&f, &bits, 4);
    return f;
}

// Cephes constants (expf, logf).
constexpr float kExpHi = 88.3762626647949f, kExpLo = -88.3762626647949f;
constexpr float kLog2e = 1.44269504088896341f, kExpC1 = 0.693359375f, kExpC2 = -2.12194440e-4f;
constexpr float kExpP0 = 1.9875691500e-4f, kExpP1 = 1.3981999507e-3f, kExpP2 = 8.3334519073e-3f,
                kExpP3 = 4.1665795894e-2f, kExpP4 = 1.6666665459e-1f, kExpP5 = 5.0000001201e-1f;
// 2^f on [-0.5, 0.5] (vexp2): a degree-4 fit of least largest relative error (Lawson's iterations).
constexpr float kExp2M0 = 0.9999992614421661f, kExp2M1 = 0.6931218147436664f, kExp2M2 = 0.2402474483964586f,
                kExp2M3 = 0.055917860281970745f, kExp2M4 = 0.009570101434058497f;
constexpr float kSqrtHalf = 0.707106781186547524f;
constexpr float kLogP[9] = {7.0376836292e-2f, -1.1514610310e-1f, 1.1676998740e-1f, -1.2420140846e-1f,
                            1.4249322787e-1f, -1.6668057665e-1f, 2.0000714765e-1f, -2.4999993993e-1f,
                            3.3333331174e-1f};

struct Scalar {
    static constexpr int W = 1;
    static constexpr const char* name = "scalar";
    using F = float;
    using M = bool;
    static F set1(float x) { return x; }
    static F load(const float* p) { return *p; }
    static F load(const uint16_t* p) { return half_to_float(*p); }
    static F load(const int8_t* p) { return float(*p); }
    static void store(float* p, F a) { *p = a; }
    static F iota() { return 0.0f; }
    static F fma(F a, F b, F c) { return a * b + c; }
    static F min(F a, F b) { return a < b ? a : b; }
    static F max(F a, F b) { return a > b ? a : b; }
    static F sqrt(F a) { return std::sqrt(a); }
    static F floor(F a) { return std::floor(a); }
    static F ceil(F a) { return std::ceil(a); }
    static M lt(F a, F b) { return a < b; }
    static M le(F a, F b) { return a <= b; }
    static M ge(F a, F b) { return a >= b; }
    static M gt(F a, F b) { return a > b; }
    static M mand(M a, M b) { return a && b; }
    static M mor(M a, M b) { return a || b; }
    static M mandnot(M a, M b) { return !a && b; }  // (not a) and b
    static M ge_and(M m, F a, F b) { return m && a >= b; }  // m and (a >= b)
    static M le_and(M m, F a, F b) { return m && a <= b; }
    static M gt_and(M m, F a, F b) { return m && a > b; }
    static F zero_unless(M m, F a) { return m ? a : 0.0f; }
    static F mul_if(M m, F a, F b) { return m ? a * b : 0.0f; }  // a b where m, else 0
    static F sub_if(M m, F a, F b) { return m ? a - b : a; }     // a - b where m, else a
    static bool any(M m) { return m; }
    static unsigned bits(M m) { return m ? 1u : 0u; }
    static F select(M m, F a, F b) { return m ? a : b; }
    static F opaque(F a) { __asm__("" : "+x"(a)); return a; }  // a value the compiler cannot fuse into an FMA
    static float hsum(F a) { return a; }
};

#if defined(BS_ISA_AVX2)
struct Avx2 {
    static constexpr int W = 8;
    static constexpr const char* name = "avx2";
    struct F {
        __m256 v;
        F() = default;
        F(__m256 x) : v(x) {}
        friend F operator+(F a, F b) { return _mm256_add_ps(a.v, b.v); }
        friend F operator-(F a, F b) { return _mm256_sub_ps(a.v, b.v); }
        friend F operator*(F a, F b) { return _mm256_mul_ps(a.v, b.v); }
        friend F operator/(F a, F b) { return _mm256_div_ps(a.v, b.v); }
        friend F operator-(F a) { return _mm256_xor_ps(a.v, _mm256_set1_ps(-0.0f)); }
        F& operator+=(F b) { v = _mm256_add_ps(v, b.v); return *this; }
        F& operator*=(F b) { v = _mm256_mul_ps(v, b.v); return *this; }
    };
    struct M {
        __m256 v;
    };
    static F set1(float x) { return _mm256_set1_ps(x); }
    static F load(const float* p) { return _mm256_loadu_ps(p); }
    static F load(const uint16_t* p) {
        return _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
    }
    static F load(const int8_t* p) {  // 8 bytes
        return _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(p))));
    }
    static void store(float* p, F a) { _mm256_storeu_ps(p, a.v); }
    static F iota() { return _mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7); }
    static F fma(F a, F b, F c) { return _mm256_fmadd_ps(a.v, b.v, c.v); }
    static F min(F a, F b) { return _mm256_min_ps(a.v, b.v); }
    static F max(F a, F b) { return _mm256_max_ps(a.v, b.v); }
    static F sqrt(F a) { return _mm256_sqrt_ps(a.v); }
    static F floor(F a) { return _mm256_floor_ps(a.v); }
    static F ceil(F a) { return _mm256_ceil_ps(a.v); }
    static M lt(F a, F b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LT_OQ)}; }
    static M le(F a, F b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LE_OQ)}; }
    static M ge(F a, F b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_GE_OQ)}; }
    static M gt(F a, F b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_GT_OQ)}; }
    static M mand(M a, M b) { return {_mm256_and_ps(a.v, b.v)}; }
    static M mor(M a, M b) { return {_mm256_or_ps(a.v, b.v)}; }
    static M mandnot(M a, M b) { return {_mm256_andnot_ps(a.v, b.v)}; }
    static M ge_and(M m, F a, F b) { return {_mm256_and_ps(m.v, _mm256_cmp_ps(a.v, b.v, _CMP_GE_OQ))}; }
    static M le_and(M m, F a, F b) { return {_mm256_and_ps(m.v, _mm256_cmp_ps(a.v, b.v, _CMP_LE_OQ))}; }
    static M gt_and(M m, F a, F b) { return {_mm256_and_ps(m.v, _mm256_cmp_ps(a.v, b.v, _CMP_GT_OQ))}; }
    static F zero_unless(M m, F a) { return _mm256_and_ps(m.v, a.v); }
    static F mul_if(M m, F a, F b) { return _mm256_and_ps(m.v, _mm256_mul_ps(a.v, b.v)); }
    static F sub_if(M m, F a, F b) { return _mm256_sub_ps(a.v, _mm256_and_ps(m.v, b.v)); }
    static bool any(M m) { return _mm256_movemask_ps(m.v) != 0; }
    static unsigned bits(M m) { return unsigned(_mm256_movemask_ps(m.v)); }
    static F select(M m, F a, F b) { return _mm256_blendv_ps(b.v, a.v, m.v); }
    static F opaque(F a) { __asm__("" : "+x"(a.v)); return a; }
    static float hsum(F a) {
        __m128 s = _mm_add_ps(_mm256_castps256_ps128(a.v), _mm256_extractf128_ps(a.v, 1));
        s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        s = _mm_add_ss(s, _mm_movehdup_ps(s));
        return _mm_cvtss_f32(s);
    }
    // y * 2^n for integral n (added to the exponent bits).
    static F ldexp(F y, F n) {
        return F(_mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(y.v),
                                                       _mm256_slli_epi32(_mm256_cvtps_epi32(n.v), 23))));
    }
    // x = m 2^e with m in [0.5, 1), for finite x > 0.
    static F frexp(F x, F& e) {
        const __m256i bits = _mm256_castps_si256(x.v);
        e = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(bits, 23), _mm256_set1_epi32(126)));
        return F(_mm256_castsi256_ps(_mm256_or_si256(_mm256_and_si256(bits, _mm256_set1_epi32(0x007fffff)),
                                                      _mm256_set1_epi32(0x3f000000))));
    }
    static F round(F x) { return _mm256_round_ps(x.v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
};
#endif

#if defined(BS_ISA_AVX512)
struct Avx512 {
    static constexpr int W = 16;
    static constexpr const char* name = "avx512";
    struct F {
        __m512 v;
        F() = default;
        F(__m512 x) : v(x) {}
        friend F operator+(F a, F b) { return _mm512_add_ps(a.v, b.v); }
        friend F operator-(F a, F b) { return _mm512_sub_ps(a.v, b.v); }
        friend F operator*(F a, F b) { return _mm512_mul_ps(a.v, b.v); }
        friend F operator/(F a, F b) { return _mm512_div_ps(a.v, b.v); }
        friend F operator-(F a) { return _mm512_sub_ps(_mm512_setzero_ps(), a.v); }
        F& operator+=(F b) { v = _mm512_add_ps(v, b.v); return *this; }
        F& operator*=(F b) { v = _mm512_mul_ps(v, b.v); return *this; }
    };
    struct M {
        __mmask16 k;
    };
    static F set1(float x) { return _mm512_set1_ps(x); }
    static F load(const float* p) { return _mm512_loadu_ps(p); }
    static F load(const uint16_t* p) {
        return _mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)));
    }
    static F load(const int8_t* p) {  // 16 bytes
        return _mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p))));
    }
    static void store(float* p, F a) { _mm512_storeu_ps(p, a.v); }
    static F iota() { return _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15); }
    static F fma(F a, F b, F c) { return _mm512_fmadd_ps(a.v, b.v, c.v); }
    static F min(F a, F b) { return _mm512_min_ps(a.v, b.v); }
    static F max(F a, F b) { return _mm512_max_ps(a.v, b.v); }
    static F sqrt(F a) { return _mm512_sqrt_ps(a.v); }
    static F floor(F a) { return _mm512_roundscale_ps(a.v, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC); }
    static F ceil(F a) { return _mm512_roundscale_ps(a.v, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC); }
    static M lt(F a, F b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LT_OQ)}; }
    static M le(F a, F b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LE_OQ)}; }
    static M ge(F a, F b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GE_OQ)}; }
    static M gt(F a, F b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GT_OQ)}; }
    static M mand(M a, M b) { return {__mmask16(a.k & b.k)}; }
    static M mor(M a, M b) { return {__mmask16(a.k | b.k)}; }
    static M mandnot(M a, M b) { return {__mmask16(~a.k & b.k)}; }
    // Compares under a write mask: the AND comes free with the compare (no separate mask instruction).
    static M ge_and(M m, F a, F b) { return {_mm512_mask_cmp_ps_mask(m.k, a.v, b.v, _CMP_GE_OQ)}; }
    static M le_and(M m, F a, F b) { return {_mm512_mask_cmp_ps_mask(m.k, a.v, b.v, _CMP_LE_OQ)}; }
    static M gt_and(M m, F a, F b) { return {_mm512_mask_cmp_ps_mask(m.k, a.v, b.v, _CMP_GT_OQ)}; }
    static F zero_unless(M m, F a) { return _mm512_maskz_mov_ps(m.k, a.v); }
    static F mul_if(M m, F a, F b) { return _mm512_maskz_mul_ps(m.k, a.v, b.v); }     // one instruction
    static F sub_if(M m, F a, F b) { return _mm512_mask_sub_ps(a.v, m.k, a.v, b.v); }  // one instruction
    static bool any(M m) { return m.k != 0; }
    static unsigned bits(M m) { return unsigned(m.k); }
    static F select(M m, F a, F b) { return _mm512_mask_blend_ps(m.k, b.v, a.v); }
    static F opaque(F a) { __asm__("" : "+v"(a.v)); return a; }
    static float hsum(F a) { return _mm512_reduce_add_ps(a.v); }
    static F ldexp(F y, F n) { return _mm512_scalef_ps(y.v, n.v); }  // y 2^n in one instruction
    static F frexp(F x, F& e) {
        const __m512i bits = _mm512_castps_si512(x.v);
        e = _mm512_cvtepi32_ps(_mm512_sub_epi32(_mm512_srli_epi32(bits, 23), _mm512_set1_epi32(126)));
        return F(_mm512_castsi512_ps(_mm512_or_si512(_mm512_and_si512(bits, _mm512_set1_epi32(0x007fffff)),
                                                      _mm512_set1_epi32(0x3f000000))));
    }
    static F round(F x) { return _mm512_roundscale_ps(x.v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
};
#endif

// exp, 2^t and log over any wrapper: one polynomial implementation for every vector path; the scalar path uses
// the C library.
template <class V>
inline typename V::F vexp(typename V::F x) {
    using F = typename V::F;
    x = V::min(V::max(x, V::set1(kExpLo)), V::set1(kExpHi));
    const F fx = V::floor(V::fma(x, V::set1(kLog2e), V::set1(0.5f)));
    x = x - fx * V::set1(kExpC1) - fx * V::set1(kExpC2);
    F y = V::fma(V::set1(kExpP0), x, V::set1(kExpP1));
    y = V::fma(y, x, V::set1(kExpP2));
    y = V::fma(y, x, V::set1(kExpP3));
    y = V::fma(y, x, V::set1(kExpP4));
    y = V::fma(y, x, V::set1(kExpP5));
    y = V::fma(y, x * x, x + V::set1(1.0f));
    return V::ldexp(y, fx);
}

// 2^t for t <= 1 (clamped below at -64): t = n + f, |f| <= 0.5, 2^f by a degree-4 polynomial fitted for the
// least largest relative error on [-0.5, 0.5] (2.7e-6 in float arithmetic), evaluated by Horner's scheme: four
// FMAs (it sits in the compositing loop, whose iterations are independent but for T: throughput, not latency).
template <class V>
inline typename V::F vexp2(typename V::F t) {
    using F = typename V::F;
    t = V::max(t, V::set1(-64.0f));  // 2^-64 is still a normal float: denormals take slow microcode paths
    const F n = V::round(t);
    const F f = t - n;
    F p = V::fma(V::set1(kExp2M4), f, V::set1(kExp2M3));
    p = V::fma(p, f, V::set1(kExp2M2));
    p = V::fma(p, f, V::set1(kExp2M1));
    p = V::fma(p, f, V::set1(kExp2M0));
    return V::ldexp(p, n);
}

// Natural log for finite x > 0.
template <class V>
inline typename V::F vlog(typename V::F x) {
    using F = typename V::F;
    F e;
    F m = V::frexp(x, e);
    const auto small = V::lt(m, V::set1(kSqrtHalf));
    e = V::select(small, e - V::set1(1.0f), e);
    m = V::select(small, m + m, m) - V::set1(1.0f);
    const F z = m * m;
    F y = V::set1(kLogP[0]);
    for (int i = 1; i < 9; ++i) y = V::fma(y, m, V::set1(kLogP[i]));
    y = y * m * z;
    y = V::fma(e, V::set1(kExpC2), y);
    y = V::fma(V::set1(-0.5f), z, y);
    return V::fma(e, V::set1(kExpC1), m + y);
}

template <>
inline float vexp<Scalar>(float x) { return std::exp(x); }
template <>
inline float vexp2<Scalar>(float t) { return std::exp2(t); }
template <>
inline float vlog<Scalar>(float x) { return std::log(x); }

}  // namespace bs
