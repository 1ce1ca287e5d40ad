// Cephes' single-precision exp (S. L. Moshier, expf.c), shared by the fused kernels' vector loops:
// e^x = 2^n e^r with n = round(x / ln 2) and r = x - n ln 2, the product n ln 2 split in two parts
// (Cody-Waite) so r keeps its low bits, and e^r by a degree-6 polynomial; about 1 ulp from libm's over
// the normal range. V is float or a GCC vector of floats (a scalar operand is broadcast), so the same
// operations run in either; each caller rounds n and builds 2^n from the exponent bits its own way.
#pragma once

namespace hico {

// r = x - n ln 2, for n an integer held as a float (or a vector of them).
template <typename V>
inline V expf_reduce(V x, V n) {
  return (x - n * 0.693359375f) - n * -2.12194440e-4f;
}

// e^r for |r| <= ln 2 / 2.
template <typename V>
inline V expf_poly(V r) {
  V p = r * 1.9875691500e-4f + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  return p * r * r + r + 1.0f;
}

}  // namespace hico
