// Tile binning (binning_cpu.cpp), compiled into the compositor's extension module, which exports it as "bin".
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <vector>

// Hidden: the two sources share it inside the module, which exports only what PYBIND11_MODULE defines.
namespace hico __attribute__((visibility("hidden"))) {

// Every (Gaussian, tile) intersection, sorted by (tile, depth):
//   means2d [G,2], conics [G,3], extents [G,2], depths [G], radii [G] int32 (G = C * N flattened), reach [N]
//   -> gaussian_ids [I], tile_ids [I], tile_offsets [T+1]
std::vector<at::Tensor> bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& reach,
                            const at::Tensor& extents, const at::Tensor& radii, const at::Tensor& depths,
                            int64_t num_cams, int64_t n, int64_t width, int64_t height,
                            int64_t tile_size);

}  // namespace hico
