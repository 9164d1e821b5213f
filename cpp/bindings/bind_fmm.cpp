// kinema._core.fmm: the 2D Laplace FMM and the direct sum behind km.fmm. Arrays arrive
// checked and C-contiguous from python/kinema/fmm.py; results are handed over without a copy.
#include <optional>

#include "bindings/common.h"
#include "fmm/laplace2d.h"
#include "fmm/laplace3d.h"

namespace kinema::bind {

namespace {

struct Inputs {
  const Scalar* sources;
  const Scalar* charges;
  const Scalar* targets;
  Index n, m;
};

Inputs inputs(py::array& sources, py::array& charges, std::optional<py::array>& targets) {
  if (sources.ndim() != 2 || sources.shape(1) != 2)
    throw InvalidArgument("sources: expected shape (n, 2)");
  const Index n = sources.shape(0);
  Inputs in{checked_data(sources, "sources", 2 * n, false), checked_data(charges, "charges", n, false),
            nullptr, n, n};
  if (targets) {
    if (targets->ndim() != 2 || targets->shape(1) != 2)
      throw InvalidArgument("targets: expected shape (m, 2)");
    in.m = targets->shape(0);
    in.targets = checked_data(*targets, "targets", 2 * in.m, false);
  }
  return in;
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
        const Inputs in = inputs(sources, charges, targets);
        fmm::Laplace2dConfig config;
        config.eps = eps;
        config.gradient = gradient;
        config.order = order;
        config.leaf_size = leaf_size;
        std::vector<Scalar> phi(static_cast<size_t>(in.m));
        std::vector<Scalar> grad(gradient ? static_cast<size_t>(2 * in.m) : 0);
        fmm::Laplace2dStats stats;
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          stats = fmm::laplace2d(in.sources, in.charges, in.n, in.targets, in.m, config, phi.data(),
                                 grad.data(), interrupt);
        }
        py::dict info;
        info["order"] = stats.order;
        info["leaf_size"] = stats.leaf_size;
        info["boxes"] = stats.box_count;
        info["depth"] = stats.depth;
        info["seconds_tree"] = stats.seconds_tree;
        info["seconds_upward"] = stats.seconds_upward;
        info["seconds_downward"] = stats.seconds_downward;
        info["seconds_leaves"] = stats.seconds_leaves;
        py::tuple out = results(std::move(phi), std::move(grad), in.m, gradient);
        return py::make_tuple(out[0], out[1], info);
      },
      py::arg("sources"), py::arg("charges"), py::arg("targets"), py::arg("eps"),
      py::arg("gradient"), py::arg("order"), py::arg("leaf_size"));
  m.def(
      "direct2d",
      [](py::array sources, py::array charges, std::optional<py::array> targets, bool gradient) {
        const Inputs in = inputs(sources, charges, targets);
        std::vector<Scalar> phi(static_cast<size_t>(in.m));
        std::vector<Scalar> grad(gradient ? static_cast<size_t>(2 * in.m) : 0);
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          fmm::direct2d(in.sources, in.charges, in.n, in.targets, in.m, gradient, phi.data(),
                        grad.data(), interrupt);
        }
        return results(std::move(phi), std::move(grad), in.m, gradient);
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
         bool direct) {
        if (sources.ndim() != 2 || sources.shape(1) != 3)
          throw InvalidArgument("sources: expected shape (n, 3)");
        const Index n = sources.shape(0);
        if (charges.ndim() != 2 || charges.shape(0) != n)
          throw InvalidArgument("charges: expected shape (n, components)");
        const int components = static_cast<int>(charges.shape(1));
        const Scalar* src = checked_data(sources, "sources", 3 * n, false);
        const Scalar* q = checked_data(charges, "charges", n * components, false);
        const Scalar* tgt = nullptr;
        Index mt = n;
        if (targets) {
          if (targets->ndim() != 2 || targets->shape(1) != 3)
            throw InvalidArgument("targets: expected shape (m, 3)");
          mt = targets->shape(0);
          tgt = checked_data(*targets, "targets", 3 * mt, false);
        }
        if (kernel < 0 || kernel > 2) throw InvalidArgument("kernel: expected 0, 1 or 2");
        fmm3::Fmm3dConfig config;
        config.eps = eps;
        config.derivatives = derivatives;
        config.order = order;
        config.leaf_size = leaf_size;
        config.kernel = static_cast<fmm3::NearKernel>(kernel);
        config.length = length;
        config.min_width = min_width;
        const int width = fmm3::output_width(derivatives);
        std::vector<Scalar> out(static_cast<size_t>(mt * components * width));
        fmm3::Fmm3dStats stats;
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          if (direct) fmm3::direct3d(src, n, q, components, tgt, mt, config, out.data(), interrupt);
          else stats = fmm3::fmm3d(src, n, q, components, tgt, mt, config, out.data(), interrupt);
        }
        py::dict info;
        info["order"] = stats.order;
        info["leaf_size"] = stats.leaf_size;
        info["boxes"] = stats.box_count;
        info["depth"] = stats.depth;
        info["seconds_tree"] = stats.seconds_tree;
        info["seconds_upward"] = stats.seconds_upward;
        info["seconds_m2l"] = stats.seconds_m2l;
        info["seconds_downward"] = stats.seconds_downward;
        info["seconds_leaves"] = stats.seconds_leaves;
        return py::make_tuple(to_numpy(std::move(out), {mt, components, width}), info);
      },
      py::arg("sources"), py::arg("charges"), py::arg("targets"), py::arg("eps"),
      py::arg("derivatives"), py::arg("kernel"), py::arg("length"), py::arg("min_width"),
      py::arg("order"), py::arg("leaf_size"), py::arg("direct"));
}

}  // namespace kinema::bind
