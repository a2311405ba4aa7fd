// The kernels of kernels.inl and backward.inl compiled for the scalar instruction set (see CMakeLists.txt for
// its flags).

#define BS_NS scalar
#include "simd.hpp"

namespace bs {
namespace scalar {
using V = Scalar;
}
}  // namespace bs

#include "kernels.inl"
#include "backward.inl"
