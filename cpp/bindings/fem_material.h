// The fem material named in Python ("linear", "stvk", "corotated", "neohookean"), shared by the
// km.fem and km.contact bindings.
#pragma once

#include <string>

#include "core/errors.h"
#include "fem/kernels.h"

namespace kinema::bind {

inline fem::Material parse_material(const std::string& name) {
  if (name == "linear") return fem::Material::Linear;
  if (name == "stvk") return fem::Material::StVK;
  if (name == "corotated") return fem::Material::Corotated;
  if (name == "neohookean") return fem::Material::NeoHookean;
  throw InvalidArgument("model: expected 'linear', 'stvk', 'corotated' or 'neohookean', got '" + name + "'");
}

}  // namespace kinema::bind
