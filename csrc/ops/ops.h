// Dispatchers: validate tensors, allocate outputs, fill the parameter structs and call the
// CPU or CUDA backend by device and dtype.
#pragma once

#include <torch/extension.h>

namespace gsw::ops {

void register_ops(pybind11::module_& m);

}  // namespace gsw::ops
