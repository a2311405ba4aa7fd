// Python bindings (nanobind) of the native CPU renderer: numpy arrays in and out, no copies, the GIL released
// while rendering. Independent of torch's ABI: render_core/raster/native.py passes tensors as numpy views.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>
#include <omp.h>

#include <algorithm>
#include <cstdlib>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "backward.hpp"
#include "pipeline.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {

template <class T>
using In = nb::ndarray<const T, nb::c_contig, nb::device::cpu>;
template <class T>
using Out = nb::ndarray<T, nb::c_contig, nb::device::cpu>;
using AnyIn = nb::ndarray<nb::c_contig, nb::device::cpu>;

void require(bool ok, const std::string& what) {
    if (!ok) throw std::invalid_argument(what);
}

template <class A>
void require_shape(const A& a, std::initializer_list<size_t> shape, const char* name) {
    bool ok = a.ndim() == shape.size();
    size_t i = 0;
    for (size_t s : shape) ok = ok && a.shape(i++) == s;
    if (!ok) {
        std::string got = "[";
        for (size_t d = 0; d < a.ndim(); ++d) got += (d ? ", " : "") + std::to_string(a.shape(d));
        std::string want = "[";
        i = 0;
        for (size_t s : shape) want += (i++ ? ", " : "") + std::to_string(s);
        throw std::invalid_argument(std::string(name) + ": expected shape " + want + "], got " + got + "]");
    }
}

bool is_f32(const AnyIn& a) { return a.dtype() == nb::dtype<float>(); }
bool is_u16(const AnyIn& a) { return a.dtype() == nb::dtype<uint16_t>(); }
bool is_i8(const AnyIn& a) { return a.dtype() == nb::dtype<int8_t>(); }

// One CSR table of blendshape pairs over the n_face face Gaussians (render_core/packed.py, "Pairs").
bs::PairsView check_pairs(const In<int32_t>& row_ptr, const In<uint16_t>& col, const AnyIn& vals, int n_face, int K,
                          int len, const char* name) {
    const std::string field(name);
    require_shape(row_ptr, {size_t(n_face) + 1}, (field + ".row_ptr").c_str());
    const int32_t* rp = row_ptr.data();
    require(rp[0] == 0, field + ".row_ptr[0] must be 0");
    for (int i = 0; i < n_face; ++i) require(rp[i + 1] >= rp[i], field + ".row_ptr must not decrease");
    const size_t nnz = size_t(rp[n_face]);
    require_shape(col, {nnz}, (field + ".col").c_str());
    for (size_t i = 0; i < nnz; ++i) require(col.data()[i] < K, field + ".col out of range");
    const size_t spare = size_t((len + 15) / 16 * 16 - len);
    require_shape(vals, {nnz * size_t(len) + spare}, (field + ".vals").c_str());
    bs::PairsView p;
    p.row_ptr = rp, p.col = col.data(), p.vals = vals.data(), p.len = len;
    return p;
}

// Scales of an int8 table, finite and not negative, shaped as expected (any other table: none).
const float* check_scales(const In<float>& scale, std::initializer_list<size_t> shape, bool quantized,
                          const std::string& name) {
    if (!quantized) {
        require(scale.size() == 0, name + ": only int8 pair values have scales");
        return nullptr;
    }
    require_shape(scale, shape, name.c_str());
    const float* s = scale.data();
    for (size_t i = 0; i < scale.size(); ++i)
        require(std::isfinite(s[i]) && s[i] >= 0.0f, name + ": scales must be finite and not negative");
    return s;
}

// The storage of the pair values (geometry and colour alike) and the int8 tables' scales and position residuals.
bs::Storage check_storage(const AnyIn& geo_vals, const AnyIn& sh_vals, const In<float>& geo_scale,
                          const In<int8_t>& geo_residual, const In<float>& sh_scale, int K, int C,
                          bs::AvatarView& v) {
    const bs::Storage storage = is_u16(geo_vals) ? bs::Storage::kF16
                                : is_i8(geo_vals) ? bs::Storage::kI8
                                                  : bs::Storage::kF32;
    require(is_f32(geo_vals) || storage != bs::Storage::kF32,
            "geometry.vals: float32, float16 bits (uint16) or int8");
    require(sh_vals.dtype() == geo_vals.dtype(), "color.vals: same storage as geometry.vals");
    const bool i8 = storage == bs::Storage::kI8;
    const size_t nnz = size_t(v.geometry.row_ptr[v.n_face]);
    v.geometry.scale = check_scales(geo_scale, {size_t(K), 16}, i8, "geometry.scale");
    require(i8 || geo_residual.size() == 0, "geometry.residual: only int8 pair values have residuals");
    if (i8) {
        require_shape(geo_residual, {nnz * bs::kPositionColumns + 13}, "geometry.residual");
        v.geometry.residual = geo_residual.data();
    }
    v.color.scale = check_scales(sh_scale, {size_t(K), size_t(3 * C + 15) / 16 * 16}, i8, "color.scale");
    return storage;
}

class NativeAvatar {
   public:
    NativeAvatar(In<float> base, In<int32_t> geo_ptr, In<uint16_t> geo_col, AnyIn geo_vals, In<int32_t> sh_ptr,
                 In<uint16_t> sh_col, AnyIn sh_vals, AnyIn pc, In<float> eyelid, In<float> lbs, In<float> joints,
                 In<int32_t> parents, int n_face, int K, int C, In<float> geo_scale, In<int8_t> geo_residual,
                 In<float> sh_scale)
        : base_(base), geo_ptr_(geo_ptr), sh_ptr_(sh_ptr), geo_col_(geo_col), sh_col_(sh_col), geo_vals_(geo_vals),
          sh_vals_(sh_vals), pc_(pc), eyelid_(eyelid), lbs_(lbs), joints_(joints), parents_(parents),
          geo_scale_(geo_scale), sh_scale_(sh_scale), geo_residual_(geo_residual) {
        require(C == 1 || C == 4 || C == 9 || C == 16, "C must be 1, 4, 9 or 16");
        const int dp = 16 + (3 * C + 15) / 16 * 16;
        require(base.ndim() == 2 && base.shape(1) == size_t(dp), "base: expected [N, 16 + ceil16(3C)]");
        const int n = int(base.shape(0));
        require(n_face >= 0 && n_face <= n, "n_face out of range");
        require(K >= 0 && K <= 65536, "at most 65536 blendshapes");
        const int J = int(joints.shape(0));
        require_shape(joints, {size_t(J), 3}, "joints");
        require(J >= 1 && J <= 32, "joints: 1 to 32 joints");
        require_shape(parents, {size_t(J)}, "parents");
        for (int j = 0; j < J; ++j)
            require(parents.data()[j] < j && (parents.data()[j] >= 0 || j == 0), "parents must precede children");
        require_shape(lbs, {size_t(J), size_t(n)}, "lbs");
        v_.n_face = n_face;
        v_.geometry = check_pairs(geo_ptr, geo_col, geo_vals, n_face, K, 11, "geometry");
        v_.color = check_pairs(sh_ptr, sh_col, sh_vals, n_face, K, 3 * C, "color");
        const bs::Storage storage = check_storage(geo_vals, sh_vals, geo_scale, geo_residual, sh_scale, K, C, v_);
        const int P = 9 * (J - 1), ppad = ((P + 15) / 16) * 16;
        if (pc.size() > 0) {
            require(storage == bs::Storage::kF32 ? is_f32(pc) : is_u16(pc),
                    "pc: float32 with float32 pair values, else float16 bits (uint16)");
            require_shape(pc, {size_t(n_face), 3, size_t(ppad)}, "pc");
        }
        if (eyelid.size() > 0) require_shape(eyelid, {size_t(n_face), 2, 3}, "eyelid");
        v_.n_total = n, v_.K = K, v_.J = J, v_.C = C, v_.Dp = dp;
        v_.P = P, v_.Ppad = ppad, v_.storage = storage;
        v_.base = base.data();
        v_.pc = pc.size() > 0 ? pc.data() : nullptr;
        v_.eyelid = eyelid.size() > 0 ? eyelid.data() : nullptr;
        v_.lbs = lbs.data(), v_.joints = joints.data(), v_.parents = parents.data();
    }
    const bs::AvatarView& view() const { return v_; }

   private:
    In<float> base_;
    In<int32_t> geo_ptr_, sh_ptr_;
    In<uint16_t> geo_col_, sh_col_;
    AnyIn geo_vals_, sh_vals_, pc_;
    In<float> eyelid_, lbs_, joints_;
    In<int32_t> parents_;
    In<float> geo_scale_, sh_scale_;  // int8 pair values' scales (else empty)
    In<int8_t> geo_residual_;         // int8 geometry's position residuals (else empty)
    bs::AvatarView v_;
};

struct Outputs {
    Out<float> rgb, alpha, depth;
};

std::vector<bs::Cam> make_cams(const In<float>& K, const In<float>& R, const In<float>& t, int B, int width,
                               int height, bool antialiased) {
    require(width >= 1 && height >= 1, "image size must be positive");
    require_shape(K, {size_t(B), 3, 3}, "K");
    require_shape(R, {size_t(B), 3, 3}, "R");
    require_shape(t, {size_t(B), 3}, "t");
    std::vector<bs::Cam> cams(B);
    for (int b = 0; b < B; ++b) {
        const float* k = K.data() + b * 9;
        bs::Cam& c = cams[b];
        c.fx = k[0], c.fy = k[4], c.cx = k[2], c.cy = k[5];
        require(c.fx > 0 && c.fy > 0, "K: focal lengths must be positive");
        for (int i = 0; i < 9; ++i) c.R[i] = R.data()[b * 9 + i];
        for (int i = 0; i < 3; ++i) c.t[i] = t.data()[b * 3 + i];
        for (int i = 0; i < 3; ++i) c.centre[i] = -(c.R[i] * c.t[0] + c.R[3 + i] * c.t[1] + c.R[6 + i] * c.t[2]);
        c.width = width, c.height = height, c.antialiased = antialiased;
    }
    return cams;
}

void check_outputs(const Outputs& o, const In<float>& bg, int B, int width, int height) {
    require_shape(bg, {size_t(B), 3}, "background");
    require_shape(o.rgb, {size_t(B), size_t(height), size_t(width), 3}, "rgb");
    require_shape(o.alpha, {size_t(B), size_t(height), size_t(width)}, "alpha");
    require_shape(o.depth, {size_t(B), size_t(height), size_t(width)}, "depth");
}

// threads <= 0: every CPU this process may use, or OMP_NUM_THREADS when set. Not omp_get_max_threads() alone: it
// follows omp_set_num_threads, which torch.set_num_threads calls for the whole process (the runtime is shared).
int thread_count(int threads) {
    if (threads > 0) return threads;
    return std::getenv("OMP_NUM_THREADS") != nullptr ? omp_get_max_threads() : omp_get_num_procs();
}

nb::dict timings(const bs::Timings& t, const bs::Kernels& k, int threads) {
    nb::dict d;
    d["blend"] = t.blend_ms, d["lbs"] = t.lbs_ms, d["raster"] = t.raster_ms, d["bin"] = t.bin_ms;
    d["isa"] = std::string(k.name), d["threads"] = threads;
    return d;
}

void check_flags(unsigned flags) {
    require((flags & ~unsigned(bs::kRasterKnown)) == 0, "flags: unknown compositing schedule bits");
}

// The inputs of render / render_rgba8: B frames and their cameras.
struct FrameInputs {
    In<float> psi, rot, eyelids, K, R, t;
    int width, height;
    bool antialiased;
};

// The frames checked against the avatar, and their cameras.
std::vector<bs::Cam> check_frames(const bs::AvatarView& av, const FrameInputs& in) {
    require(in.psi.ndim() == 2 && in.psi.shape(1) == size_t(av.K), "expression: expected [B, K]");
    const int B = int(in.psi.shape(0));
    require(B >= 1, "expression: empty batch");
    require_shape(in.rot, {size_t(B), size_t(av.J), 3, 3}, "joint_rotations");
    require_shape(in.eyelids, {size_t(B), 2}, "eyelids");
    return make_cams(in.K, in.R, in.t, B, in.width, in.height, in.antialiased);
}

// The fused pipeline of render / render_rgba8 on checked inputs, into out.
nb::dict render_into(const NativeAvatar& avatar, const FrameInputs& in, const std::vector<bs::Cam>& cams,
                     const In<float>& bg, const bs::FrameOut& out, const std::string& isa, int threads,
                     unsigned flags) {
    const bs::Kernels& k = bs::select_kernels(isa);
    const int nt = thread_count(threads);
    check_flags(flags);
    bs::Timings tm;
    {
        nb::gil_scoped_release release;
        tm = bs::render_fused(avatar.view(), in.psi.data(), in.rot.data(), in.eyelids.data(), cams.data(),
                              int(cams.size()), bg.data(), out, k, nt, flags);
    }
    return timings(tm, k, nt);
}

nb::dict render(const NativeAvatar& avatar, In<float> psi, In<float> rot, In<float> eyelids, In<float> K,
                In<float> R, In<float> t, int width, int height, bool antialiased, In<float> bg, Out<float> rgb,
                Out<float> alpha, Out<float> depth, const std::string& isa, int threads, unsigned flags) {
    const FrameInputs in{psi, rot, eyelids, K, R, t, width, height, antialiased};
    const auto cams = check_frames(avatar.view(), in);
    check_outputs(Outputs{rgb, alpha, depth}, bg, int(cams.size()), width, height);
    bs::FrameOut out;
    out.rgb = rgb.data(), out.alpha = alpha.data(), out.depth = depth.data();
    return render_into(avatar, in, cams, bg, out, isa, threads, flags);
}

// As render, straight to 8-bit RGBA [B, H, W, 4] (what to_rgba8 makes of render's rgb and alpha, bit for bit),
// without the float images.
nb::dict render_rgba8(const NativeAvatar& avatar, In<float> psi, In<float> rot, In<float> eyelids, In<float> K,
                      In<float> R, In<float> t, int width, int height, bool antialiased, In<float> bg,
                      Out<uint8_t> rgba8, const std::string& isa, int threads, unsigned flags) {
    const FrameInputs in{psi, rot, eyelids, K, R, t, width, height, antialiased};
    const auto cams = check_frames(avatar.view(), in);
    require_shape(bg, {cams.size(), 3}, "background");
    require_shape(rgba8, {cams.size(), size_t(height), size_t(width), 4}, "rgba8");
    bs::FrameOut out;
    out.rgba8 = rgba8.data();
    return render_into(avatar, in, cams, bg, out, isa, threads, flags);
}

struct PosedInputs {
    In<float> means, quats, scales, opacities, colors;
};

size_t check_posed(const PosedInputs& in, size_t& N) {
    require(in.means.ndim() == 3 && in.means.shape(2) == 3, "means: expected [B, N, 3]");
    const size_t B = in.means.shape(0);
    N = in.means.shape(1);
    require(B >= 1, "means: empty batch");
    require_shape(in.quats, {B, N, 4}, "quats");
    require_shape(in.scales, {B, N, 3}, "scales");
    require_shape(in.opacities, {B, N}, "opacities");
    require_shape(in.colors, {B, N, 3}, "colors");
    return B;
}

nb::dict rasterize(In<float> means, In<float> quats, In<float> scales, In<float> opacities, In<float> colors,
                   In<float> K, In<float> R, In<float> t, int width, int height, bool antialiased, In<float> bg,
                   Out<float> rgb, Out<float> alpha, Out<float> depth, const std::string& isa, int threads,
                   unsigned flags) {
    size_t N = 0;
    const size_t B = check_posed({means, quats, scales, opacities, colors}, N);
    auto cams = make_cams(K, R, t, int(B), width, height, antialiased);
    Outputs o{rgb, alpha, depth};
    check_outputs(o, bg, int(B), width, height);
    const bs::Kernels& k = bs::select_kernels(isa);
    const int nt = thread_count(threads);
    bs::PosedView pv{means.data(), quats.data(), scales.data(), opacities.data(), colors.data(), int(N)};
    check_flags(flags);
    bs::FrameOut out;
    out.rgb = rgb.data(), out.alpha = alpha.data(), out.depth = depth.data();
    bs::Timings tm;
    {
        nb::gil_scoped_release release;
        tm = bs::render_posed(pv, cams.data(), int(B), bg.data(), out, k, nt, flags);
    }
    return timings(tm, k, nt);
}

// What a training forward keeps for its backward (see backward.hpp); Python holds it until the backward.
struct TrainContext {
    bs::RasterContext ctx;
};


// The forward of rasterize() that also returns a context for rasterize_backward: (timings, context).
nb::tuple rasterize_train(In<float> means, In<float> quats, In<float> scales, In<float> opacities, In<float> colors,
                          In<float> K, In<float> R, In<float> t, int width, int height, bool antialiased,
                          In<float> bg, Out<float> rgb, Out<float> alpha, Out<float> depth, const std::string& isa,
                          int threads) {
    size_t N = 0;
    const size_t B = check_posed({means, quats, scales, opacities, colors}, N);
    auto cams = make_cams(K, R, t, int(B), width, height, antialiased);
    Outputs o{rgb, alpha, depth};
    check_outputs(o, bg, int(B), width, height);
    const bs::Kernels& k = bs::select_kernels(isa);
    const int nt = thread_count(threads);
    bs::PosedView pv{means.data(), quats.data(), scales.data(), opacities.data(), colors.data(), int(N)};
    auto ctx = std::make_unique<TrainContext>();
    bs::Timings tm;
    {
        nb::gil_scoped_release release;
        tm = bs::rasterize_train(pv, cams.data(), int(B), bg.data(), rgb.data(), alpha.data(), depth.data(), k, nt,
                                 ctx->ctx);
    }
    nb::object handle = nb::cast(ctx.release(), nb::rv_policy::take_ownership);
    return nb::make_tuple(timings(tm, k, nt), handle);
}

// Gradients of a loss w.r.t. the inputs of the forward that made ctx, given dL/drgb and dL/dalpha. Writes
// [B, N, ...] gradients of means, quats, scales, opacities, colours and the [B, 3] background gradient.
nb::dict rasterize_backward(const TrainContext& c, In<float> means, In<float> quats, In<float> scales,
                            In<float> opacities, In<float> bg, In<float> grad_rgb, In<float> grad_alpha,
                            Out<float> g_means, Out<float> g_quats, Out<float> g_scales, Out<float> g_opacities,
                            Out<float> g_colors, Out<float> g_bg, int threads) {
    const bs::RasterContext& ctx = c.ctx;
    require(ctx.kb != nullptr, "rasterize_backward: the context holds no forward");
    const size_t B = ctx.B, N = ctx.N, H = ctx.height, W = ctx.width;
    require_shape(means, {B, N, 3}, "means");
    require_shape(quats, {B, N, 4}, "quats");
    require_shape(scales, {B, N, 3}, "scales");
    require_shape(opacities, {B, N}, "opacities");
    require_shape(bg, {B, 3}, "background");
    require_shape(grad_rgb, {B, H, W, 3}, "grad_rgb");
    require_shape(grad_alpha, {B, H, W}, "grad_alpha");
    require_shape(g_means, {B, N, 3}, "grad_means");
    require_shape(g_quats, {B, N, 4}, "grad_quats");
    require_shape(g_scales, {B, N, 3}, "grad_scales");
    require_shape(g_opacities, {B, N}, "grad_opacities");
    require_shape(g_colors, {B, N, 3}, "grad_colors");
    require_shape(g_bg, {B, 3}, "grad_background");
    const int nt = thread_count(threads);
    bs::PosedView pv{means.data(), quats.data(), scales.data(), opacities.data(), nullptr, int(N)};
    bs::PosedGrads g{g_means.data(), g_quats.data(), g_scales.data(), g_opacities.data(), g_colors.data()};
    bs::BackwardTimings tm;
    {
        nb::gil_scoped_release release;
        tm = bs::rasterize_backward(ctx, pv, bg.data(), grad_rgb.data(), grad_alpha.data(), g, nt);
        // dL/dbackground = sum over pixels of T dL/drgb (in double, pixel order: deterministic).
        const float* gr = grad_rgb.data();
        float* gb = g_bg.data();
#pragma omp parallel for num_threads(nt) schedule(static)
        for (int b = 0; b < int(B); ++b) {
            const float* T = ctx.frames[b].T.data();
            const float* grb = gr + size_t(b) * H * W * 3;
            double s[3] = {0.0, 0.0, 0.0};
            for (size_t p = 0; p < H * W; ++p)
                for (int e = 0; e < 3; ++e) s[e] += double(T[p]) * grb[3 * p + e];
            for (int e = 0; e < 3; ++e) gb[3 * b + e] = float(s[e]);
        }
    }
    nb::dict d;
    d["raster"] = tm.raster_ms, d["project"] = tm.project_ms;
    d["isa"] = std::string(ctx.kb->name), d["threads"] = nt;
    return d;
}

// [B, H, W, 3] colour and [B, H, W] alpha in [0, 1] -> [B, H, W, 4] 8-bit RGBA, rounded (what encoders take).
void to_rgba8(In<float> rgb, In<float> alpha, Out<uint8_t> out, int threads) {
    require(rgb.ndim() == 4 && rgb.shape(3) == 3, "rgb: expected [B, H, W, 3]");
    require_shape(alpha, {rgb.shape(0), rgb.shape(1), rgb.shape(2)}, "alpha");
    require_shape(out, {rgb.shape(0), rgb.shape(1), rgb.shape(2), 4}, "out");
    const int64_t n = int64_t(alpha.size());
    const float* c = rgb.data();
    const float* a = alpha.data();
    uint8_t* o = out.data();
    const int nt = thread_count(threads);
    auto q = [](float x) { return uint8_t(std::min(std::max(x, 0.0f), 1.0f) * 255.0f + 0.5f); };
    nb::gil_scoped_release release;
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t i = 0; i < n; ++i) {
        o[4 * i] = q(c[3 * i]), o[4 * i + 1] = q(c[3 * i + 1]), o[4 * i + 2] = q(c[3 * i + 2]), o[4 * i + 3] = q(a[i]);
    }
}

// [H, W, 4] RGBA8 -> the planes of a YUV 4:2:0 frame (what the H.264 and VP8 encoders take): BT.601 studio range,
// as FFmpeg's swscale converts by default. Y per pixel; U and V from the sums of each 2x2 block (an odd last row or
// column counted twice). Integer arithmetic, rounded half up (media/pixels.py's numpy version is the same, bit for
// bit). Planes are [rows, line size] with the line size >= the plane's width (FFmpeg pads rows). Holds the GIL: a
// 512x512 frame takes about 0.1 ms, less than getting the GIL back could cost beside a busy Python thread.
// The arithmetic, compiled for AVX2 as well as the baseline (the CPU picks at load time).
__attribute__((target_clones("avx2", "default")))
void i420_rows(const uint8_t* src, int64_t H, int64_t W, uint8_t* py, int64_t ys, uint8_t* pu, int64_t us,
               uint8_t* pv, int64_t vs) {
    for (int64_t r = 0; r < H; ++r) {
        const uint8_t* s = src + r * W * 4;
        uint8_t* o = py + r * ys;
        for (int64_t x = 0; x < W; ++x) {
            const int R = s[4 * x], G = s[4 * x + 1], B = s[4 * x + 2];
            o[x] = uint8_t(((66 * R + 129 * G + 25 * B + 128) >> 8) + 16);
        }
    }
    const int64_t ch = (H + 1) / 2, cw = (W + 1) / 2, even = W / 2;
    for (int64_t r = 0; r < ch; ++r) {
        const uint8_t* s0 = src + (2 * r) * W * 4;
        const uint8_t* s1 = src + std::min(2 * r + 1, H - 1) * W * 4;
        uint8_t *ou = pu + r * us, *ov = pv + r * vs;
        for (int64_t x = 0; x < cw; ++x) {
            const int64_t a = 8 * x, b = x < even ? a + 4 : a;  // an odd last column: its pixel twice
            const int R = s0[a] + s0[b] + s1[a] + s1[b];
            const int G = s0[a + 1] + s0[b + 1] + s1[a + 1] + s1[b + 1];
            const int B = s0[a + 2] + s0[b + 2] + s1[a + 2] + s1[b + 2];
            ou[x] = uint8_t(((-38 * R - 74 * G + 112 * B + 512) >> 10) + 128);
            ov[x] = uint8_t(((112 * R - 94 * G - 18 * B + 512) >> 10) + 128);
        }
    }
}

void rgba8_to_i420(In<uint8_t> rgba, Out<uint8_t> y, Out<uint8_t> u, Out<uint8_t> v) {
    require(rgba.ndim() == 3 && rgba.shape(2) == 4, "rgba: expected [H, W, 4]");
    const int64_t H = int64_t(rgba.shape(0)), W = int64_t(rgba.shape(1)), ch = (H + 1) / 2, cw = (W + 1) / 2;
    require(y.ndim() == 2 && int64_t(y.shape(0)) == H && int64_t(y.shape(1)) >= W, "y: expected [H, >= W]");
    require(u.ndim() == 2 && int64_t(u.shape(0)) == ch && int64_t(u.shape(1)) >= cw, "u: expected [(H+1)/2, >= (W+1)/2]");
    require(v.ndim() == 2 && int64_t(v.shape(0)) == ch && int64_t(v.shape(1)) >= cw, "v: expected [(H+1)/2, >= (W+1)/2]");
    i420_rows(rgba.data(), H, W, y.data(), int64_t(y.shape(1)), u.data(), int64_t(u.shape(1)), v.data(),
              int64_t(v.shape(1)));
}

// Best-of-five parallel read of nbytes (uint64 sums): the memory bandwidth a streaming blend can reach.
nb::dict bandwidth_probe(size_t nbytes, int threads) {
    const int nt = thread_count(threads);
    const size_t n = std::max<size_t>(nbytes / 8, 1);
    std::vector<uint64_t> buf(n);
    double best = 1e30;
    uint64_t sink = 0;
    {
        nb::gil_scoped_release release;
#pragma omp parallel for num_threads(nt) schedule(static)
        for (size_t i = 0; i < n; ++i) buf[i] = i;
        for (int pass = 0; pass < 5; ++pass) {
            const double t0 = omp_get_wtime();
            uint64_t total = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+ : total)
            for (size_t i = 0; i < n; ++i) total += buf[i];
            best = std::min(best, omp_get_wtime() - t0);
            sink += total;
        }
    }
    nb::dict d;
    d["bytes"] = n * 8, d["ms"] = best * 1e3, d["gbps"] = double(n * 8) / best / 1e9, d["threads"] = nt;
    d["checksum"] = sink;
    return d;
}

}  // namespace

NB_MODULE(_native, m) {
    m.doc() = "Blendsplat's native CPU renderer (fused blend + skinning + tile rasterizer).";
    // Avatars still referenced at interpreter exit (a server thread's cache, a daemon thread) are reclaimed by the
    // OS; nanobind's exit-time report would flag them as leaks although nothing leaks while the process runs.
    nb::set_leak_warnings(false);
    nb::class_<NativeAvatar>(m, "NativeAvatar")
        .def(nb::init<In<float>, In<int32_t>, In<uint16_t>, AnyIn, In<int32_t>, In<uint16_t>, AnyIn, AnyIn,
                      In<float>, In<float>, In<float>, In<int32_t>, int, int, int, In<float>, In<int8_t>, In<float>>(),
             "base"_a, "geo_ptr"_a, "geo_col"_a, "geo_vals"_a, "sh_ptr"_a, "sh_col"_a, "sh_vals"_a, "pc"_a,
             "eyelid"_a, "lbs"_a, "joints"_a, "parents"_a, "n_face"_a, "K"_a, "C"_a, "geo_scale"_a,
             "geo_residual"_a, "sh_scale"_a);
    const unsigned schedule = bs::kRasterDefault;
    m.attr("LAZY_TILES") = unsigned(bs::kLazyTiles);
    m.attr("SQUARE_BLOCKS") = unsigned(bs::kSquareBlocks);
    m.attr("EIGHT_BIT_STOP") = unsigned(bs::kEightBitStop);
    m.def("render", &render, "avatar"_a, "expression"_a, "joint_rotations"_a, "eyelids"_a, "K"_a, "R"_a, "t"_a,
          "width"_a, "height"_a, "antialiased"_a, "background"_a, "rgb"_a, "alpha"_a, "depth"_a, "isa"_a = "auto",
          "threads"_a = 0, "flags"_a = schedule);
    m.def("render_rgba8", &render_rgba8, "avatar"_a, "expression"_a, "joint_rotations"_a, "eyelids"_a, "K"_a, "R"_a,
          "t"_a, "width"_a, "height"_a, "antialiased"_a, "background"_a, "rgba8"_a, "isa"_a = "auto", "threads"_a = 0,
          "flags"_a = schedule);
    m.def("rasterize", &rasterize, "means"_a, "quats"_a, "scales"_a, "opacities"_a, "colors"_a, "K"_a, "R"_a, "t"_a,
          "width"_a, "height"_a, "antialiased"_a, "background"_a, "rgb"_a, "alpha"_a, "depth"_a, "isa"_a = "auto",
          "threads"_a = 0, "flags"_a = schedule);
    nb::class_<TrainContext>(m, "RasterContext",
                             "What a training forward keeps for its backward (projected splats, tile lists as "
                             "Gaussian indices, per-pixel final transmittance and last contributor).")
        .def_prop_ro("nbytes", [](const TrainContext& c) { return c.ctx.nbytes(); })
        .def_prop_ro("pairs", [](const TrainContext& c) { return c.ctx.pairs(); })
        .def_prop_ro("isa", [](const TrainContext& c) { return std::string(c.ctx.kb ? c.ctx.kb->name : ""); });
    m.def("rasterize_train", &rasterize_train, "means"_a, "quats"_a, "scales"_a, "opacities"_a, "colors"_a, "K"_a,
          "R"_a, "t"_a, "width"_a, "height"_a, "antialiased"_a, "background"_a, "rgb"_a, "alpha"_a, "depth"_a,
          "isa"_a = "auto", "threads"_a = 0);
    m.def("rasterize_backward", &rasterize_backward, "context"_a, "means"_a, "quats"_a, "scales"_a, "opacities"_a,
          "background"_a, "grad_rgb"_a, "grad_alpha"_a, "grad_means"_a, "grad_quats"_a, "grad_scales"_a,
          "grad_opacities"_a, "grad_colors"_a, "grad_background"_a, "threads"_a = 0);
    m.def("to_rgba8", &to_rgba8, "rgb"_a, "alpha"_a, "out"_a, "threads"_a = 0);
    m.def("rgba8_to_i420", &rgba8_to_i420, "rgba"_a, "y"_a, "u"_a, "v"_a);
    m.def("available_isas", &bs::available_isas, "SIMD paths this build can run here, slowest first.");
    m.def("bandwidth_probe", &bandwidth_probe, "nbytes"_a, "threads"_a = 0);
    m.def("max_threads", []() { return thread_count(0); });
}
