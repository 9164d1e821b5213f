// kinema._core.fmm: the 2D Laplace FMM and the direct sum behind km.fmm. Arrays arrive
// checked and C-contiguous from python/kinema/fmm.py; results are handed over without a copy.
#include <optional>
#include <string>
#include <type_traits>

#include "bindings/common.h"
#include "fmm/laplace2d.h"
#include "fmm/laplace3d.h"

namespace kinema::bind {

namespace {

// Points of shape (count, dim), checked and C-contiguous.
struct Points {
  const Scalar* data = nullptr;
  Index count = 0;
};

Points points(py::array& a, int dim, const char* name) {
  if (a.ndim() != 2 || a.shape(1) != dim)
    throw InvalidArgument(std::string(name) + ": expected shape (n, " + std::to_string(dim) + ")");
  return {checked_data(a, name, dim * a.shape(0), false), a.shape(0)};
}

// Targets, or the sources themselves (a null pointer with the sources' count) when absent.
Points targets_or_sources(std::optional<py::array>& targets, int dim, const Points& sources) {
  return targets ? points(*targets, dim, "targets") : Points{nullptr, sources.count};
}

// The statistics of one FMM call as the dict behind km.fmm.last_info().
template <class Stats>
py::dict info(const Stats& stats) {
  py::dict d;
  d["order"] = stats.order;
  d["leaf_size"] = stats.leaf_size;
  d["boxes"] = stats.box_count;
  d["depth"] = stats.depth;
  d["seconds_tree"] = stats.seconds_tree;
  d["seconds_upward"] = stats.seconds_upward;
  if constexpr (std::is_same_v<Stats, fmm3::Fmm3dStats>) d["seconds_m2l"] = stats.seconds_m2l;
  if constexpr (std::is_same_v<Stats, fmm3::Fmm3dStats>) d["m2l"] = stats.rotation ? "rotation" : "dense";
  if constexpr (std::is_same_v<Stats, fmm3::Fmm3dStats>) d["root_scale"] = stats.root_scale;
  if constexpr (std::is_same_v<Stats, fmm3::Fmm3dStats>) d["coincident"] = stats.coincident;
  d["seconds_downward"] = stats.seconds_downward;
  d["seconds_leaves"] = stats.seconds_leaves;
  return d;
}

py::tuple results(std::vector<Scalar>&& phi, std::vector<Scalar>&& grad, Index m, bool gradient) {
  py::object g = py::none();
  if (gradient) g = to_numpy(std::move(grad), {m, 2});
  return py::make_tuple(to_numpy(std::move(phi), {m}), g);
}

}  // namespace

void bind_fmm3d(py::module_& m);

void bind_fmm(py::module_& m) {
  m.def(
      "laplace2d",
      [](py::array sources, py::array charges, std::optional<py::array> targets, Scalar eps,
         bool gradient, int order, Index leaf_size) {
        const Points src = points(sources, 2, "sources"), tgt = targets_or_sources(targets, 2, src);
        const Scalar* q = checked_data(charges, "charges", src.count, false);
        fmm::Laplace2dConfig config;
        config.eps = eps;
        config.gradient = gradient;
        config.order = order;
        config.leaf_size = leaf_size;
        std::vector<Scalar> phi(static_cast<size_t>(tgt.count));
        std::vector<Scalar> grad(gradient ? static_cast<size_t>(2 * tgt.count) : 0);
        fmm::Laplace2dStats stats;
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          stats = fmm::laplace2d(src.data, q, src.count, tgt.data, tgt.count, config, phi.data(),
                                 grad.data(), interrupt);
        }
        py::tuple out = results(std::move(phi), std::move(grad), tgt.count, gradient);
        return py::make_tuple(out[0], out[1], info(stats));
      },
      py::arg("sources"), py::arg("charges"), py::arg("targets"), py::arg("eps"),
      py::arg("gradient"), py::arg("order"), py::arg("leaf_size"));
  m.def(
      "direct2d",
      [](py::array sources, py::array charges, std::optional<py::array> targets, bool gradient) {
        const Points src = points(sources, 2, "sources"), tgt = targets_or_sources(targets, 2, src);
        const Scalar* q = checked_data(charges, "charges", src.count, false);
        std::vector<Scalar> phi(static_cast<size_t>(tgt.count));
        std::vector<Scalar> grad(gradient ? static_cast<size_t>(2 * tgt.count) : 0);
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          fmm::direct2d(src.data, q, src.count, tgt.data, tgt.count, gradient, phi.data(),
                        grad.data(), interrupt);
        }
        return results(std::move(phi), std::move(grad), tgt.count, gradient);
      },
      py::arg("sources"), py::arg("charges"), py::arg("targets"), py::arg("gradient"));
  bind_fmm3d(m);
}

// The 3D FMM and direct sum behind km.fmm.laplace3d, km.nbody and km.vortex: charges of
// shape (n, components); returns (out of shape (m, components, width), info) with width 1, 4
// or 10 (phi; grad; hess xx xy xz yy yz zz).
void bind_fmm3d(py::module_& m) {
  m.def(
      "eval3d",
      [](py::array sources, py::array charges, std::optional<py::array> targets, Scalar eps,
         int derivatives, int kernel, Scalar length, Scalar min_width, int order, Index leaf_size,
         bool direct, int m2l) {
        const Points src = points(sources, 3, "sources"), tgt = targets_or_sources(targets, 3, src);
        const Index n = src.count, mt = tgt.count;
        if (charges.ndim() != 2 || charges.shape(0) != n)
          throw InvalidArgument("charges: expected shape (n, components)");
        const int components = static_cast<int>(charges.shape(1));
        const Scalar* q = checked_data(charges, "charges", n * components, false);
        if (kernel < 0 || kernel > 2) throw InvalidArgument("kernel: expected 0, 1 or 2");
        fmm3::Fmm3dConfig config;
        config.eps = eps;
        config.derivatives = derivatives;
        config.order = order;
        config.leaf_size = leaf_size;
        config.kernel = static_cast<fmm3::NearKernel>(kernel);
        config.length = length;
        config.min_width = min_width;
        config.m2l = static_cast<fmm3::M2lMethod>(m2l);
        const int width = fmm3::output_width(derivatives);
        std::vector<Scalar> out(static_cast<size_t>(mt * components * width));
        fmm3::Fmm3dStats stats;
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          if (direct) stats.coincident = fmm3::direct3d(src.data, n, q, components, tgt.data, mt, config, out.data(), interrupt);
          else stats = fmm3::fmm3d(src.data, n, q, components, tgt.data, mt, config, out.data(), interrupt);
        }
        return py::make_tuple(to_numpy(std::move(out), {mt, components, width}), info(stats));
      },
      py::arg("sources"), py::arg("charges"), py::arg("targets"), py::arg("eps"),
      py::arg("derivatives"), py::arg("kernel"), py::arg("length"), py::arg("min_width"),
      py::arg("order"), py::arg("leaf_size"), py::arg("direct"), py::arg("m2l") = 0);
}

}  // namespace kinema::bind
