/*=========================================================================
 *
 *  DynamicMeshRegistration
 *
 *  Licensed under the Apache License, Version 2.0 (the "License");
 *  you may not use this file except in compliance with the License.
 *  You may obtain a copy of the License at
 *
 *         http://www.apache.org/licenses/LICENSE-2.0.txt
 *
 *  Unless required by applicable law or agreed to in writing, software
 *  distributed under the License is distributed on an "AS IS" BASIS,
 *  WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
 *  See the License for the specific language governing permissions and
 *  limitations under the License.
 *
 *=========================================================================*/
#ifndef dmrBackEndRounding_h
#define dmrBackEndRounding_h

#include <cmath>

namespace itk
{
namespace dmr
{
/** x rounded to a 24-bit significand (single precision's), to nearest with ties to even, in double's exponent range
 * (no overflow or underflow as a cast to float would have); NaN, infinities and 0 are returned as they are.
 *
 * For the run's scalars derived from sums over the whole image (alpha from the mean |f|^2, beta from the MSSD at
 * iteration 1): the CPU sums in chunks, the GPU in blocks, so the two back-ends get those sums with different last
 * bits (about 1e-14 relative on a 256 x 256 x 132 pair). Used as they are, beta and alpha differ by as much, which
 * moves a float field or density value across a rounding boundary every few iterations; the fields then part by a few
 * 1e-6 mm. Rounded to 24 bits (a relative step of 6e-8), both back-ends get the same value unless their two sums
 * straddle a rounding boundary, which happens with a probability of about 1e-14 / 6e-8 per value. The density is single
 * precision anyway, and beta's paper rule (an energy ratio of 0.02) is not defined to 8 digits. */
inline double
RoundToSingleSignificand(double x)
{
  if (!std::isfinite(x) || x == 0.0)
  {
    return x;
  }
  int          exponent = 0;
  const double fraction = std::frexp(x, &exponent); // |fraction| in [0.5, 1)
  // fraction x 2^24 is exact; nearbyint rounds it to an integer with the current rounding mode (to nearest, even)
  return std::ldexp(std::nearbyint(std::ldexp(fraction, 24)), exponent - 24);
}
} // namespace dmr
} // namespace itk

#endif
