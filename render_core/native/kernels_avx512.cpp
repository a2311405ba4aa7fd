// The kernels of kernels.inl and backward.inl compiled for the avx512 instruction set (see CMakeLists.txt for
// its flags).
#define BS_ISA_AVX512
#define BS_NS avx512
#include "simd.hpp"

namespace bs {
namespace avx512 {
using V = Avx512;
}
}  // namespace bs

#include "kernels.inl"
#include "backward.inl"
