// The kernels of kernels.inl and backward.inl compiled for the avx2 instruction set (see CMakeLists.txt for
// its flags).
#define BS_ISA_AVX2
#define BS_NS avx2
#include "simd.hpp"

namespace bs {
namespace avx2 {
using V = Avx2;
}
}  // namespace bs

#include "kernels.inl"
#include "backward.inl"
