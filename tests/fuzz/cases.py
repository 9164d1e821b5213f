"""The API fuzz cases: bad and edge calls across kinema's public API, as source code.

Each public entry point has a base call that is valid; a case replaces one argument of it by a
value from the list for that argument's kind (numbers, counts, arrays, shapes, names). Further
cases write NaN into state views and query, copy simulation objects, and ask for absurd
sizes. A case is a dict: ``id``, ``setup`` (statements), ``expr`` (whose value is the result),
``arg`` (the argument being fuzzed, which a clean ValueError should name), ``interrupt`` (seconds
after which the runner sends SIGINT: the case must answer Ctrl-C) and ``fast`` (part of the
default subset).
"""

from __future__ import annotations

# Values by argument kind, as source. The first few of each list form the fast subset.
REAL = ["float('nan')", "float('inf')", "-1.0", "0.0", "1j", "None", "'x'", "1e308", "5e-324",
        "2**1100", "-1e308", "True", "[1.0, 2.0]", "np.float64(1e-308)", "np.array(1.0)"]
COUNT = ["0", "-1", "2**63", "2.5", "None", "'3'", "True", "2**31", "-2**63", "2**100",
         "np.int64(-5)", "float('nan')", "1j"]
NAME = ["'nope'", "None", "3", "''", "b'x'", "['a']"]
VECTOR = ["[float('nan'), 0.0]", "[1j, 0.0]", "[]", "[1e308, 1e308]", "'ab'", "None",
          "[[1.0]]", "[0.0]*7", "[5e-324, 5e-324]", "[2**1100, 0]"]


def array_values(base):
    """Bad variants of the array whose source is ``base``."""
    b = f"np.asarray({base}, dtype=float)"
    return [f"{b} * np.nan", f"{b}.astype(complex) + 1j", f"{b}[..., :0]", f"{b} * 1e308",
            f"{b} * 5e-324", "None", f"{b}.ravel()", f"{b}[None]", f"{b}.astype(object)",
            f"{b}.tolist()", f"{b}.astype(np.float32)", f"{b}.T", f"np.asfortranarray({b})",
            "'abc'", f"{b} * np.inf", f"np.full(np.shape({b}), 10**400, dtype=object)"]


def index_values(base):
    b = f"np.asarray({base})"
    return [f"{b} + 10**6", f"-{b} - 1", f"{b}.astype(float)", f"{b}.astype(np.uint8)",
            f"{b}[:0]", f"{b}.ravel()", f"{b} * 0 + 2**62", "None", f"{b}.astype(complex)"]


SETUP = """
import numpy as np
import kinema as km
rng = np.random.default_rng(0)
SP = __import__('scipy.sparse', fromlist=['x'])
SPD = SP.diags([-np.ones(15), 2.5 * np.ones(16), -np.ones(15)], [-1, 0, 1]).tocsr()
MS_X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
FEM_V, FEM_E = km.fem.rectangle_mesh([0, 0], [1, 1], (2, 2))
SPH_X = km.sph.block([0, 0], [0.1, 0.1], 0.02)
CAM = km.render.Camera([0, 0, 5], [0, 0, 0], width=16, height=12)
"""

# entry point -> (base call template with {name} slots, {name: (kind, base source)})
ENTRIES = {
    "poisson.solve": ("km.poisson.solve({f}, {h}, bc={bc}, method={method}, tol={tol}, max_iter={max_iter})",
                      {"f": ("array", "np.ones((16, 16))"), "h": ("real", "1/16"), "bc": ("name", "'dirichlet'"),
                       "method": ("name", "'mgpcg'"), "tol": ("real", "1e-8"), "max_iter": ("count", "None")}),
    "poisson.laplacian": ("km.poisson.laplacian({u}, {h})",
                          {"u": ("array", "np.ones((8, 8))"), "h": ("real", "0.1")}),
    "poisson.matrix": ("km.poisson.matrix({shape}, {h})",
                       {"shape": ("vector", "(8, 8)"), "h": ("real", "0.1")}),
    "poisson.Solver": ("km.poisson.Solver({shape}, {h}, shift={shift}).solve(np.ones((8, 8)))",
                       {"shape": ("vector", "(8, 8)"), "h": ("real", "0.1"), "shift": ("real", "0.0")}),
    "sparse.cholesky": ("km.sparse.cholesky(SP.csr_matrix({A})).solve({b})",
                        {"A": ("array", "SPD.toarray()"), "b": ("array", "np.ones(16)")}),
    "sparse.cg": ("km.sparse.cg(SPD, {b}, tol={tol}, max_iter={max_iter})",
                  {"b": ("array", "np.ones(16)"), "tol": ("real", "1e-8"), "max_iter": ("count", "100")}),
    "diffusion.step": ("km.diffusion.step({T}, {kappa}, {dt}, {h}, scheme={scheme}, steps={steps})",
                       {"T": ("array", "np.ones((8, 8))"), "kappa": ("real", "1.0"), "dt": ("real", "1e-3"),
                        "h": ("real", "0.1"), "scheme": ("name", "'implicit'"), "steps": ("count", "2")}),
    "diffusion.stable_dt": ("km.diffusion.stable_dt({h}, {kappa}, {d})",
                            {"h": ("real", "0.1"), "kappa": ("real", "1.0"), "d": ("count", "2")}),
    "fmm.laplace2d": ("km.fmm.laplace2d({sources}, {charges}, eps={eps}, order={order})",
                      {"sources": ("array", "rng.random((50, 2))"), "charges": ("array", "np.ones(50)"),
                       "eps": ("real", "1e-10"), "order": ("count", "None")}),
    "fmm.direct2d": ("km.fmm.direct2d({sources}, {charges})",
                     {"sources": ("array", "rng.random((20, 2))"), "charges": ("array", "np.ones(20)")}),
    "grid.Fluid": ("km.grid.Fluid({shape}, {h}, gravity={gravity}, viscosity={viscosity}, tol={tol}, "
                   "max_iter={max_iter}).step({dt})",
                   {"shape": ("vector", "(8, 8)"), "h": ("real", "0.1"), "gravity": ("vector", "[0.0, -9.8]"),
                    "viscosity": ("real", "0.0"), "tol": ("real", "1e-6"), "max_iter": ("count", "None"),
                    "dt": ("real", "0.01")}),
    "grid.advect": ("km.grid.advect({q}, ({u}, np.zeros((8, 9))), {dt}, {h})",
                    {"q": ("array", "np.ones((8, 8))"), "u": ("array", "np.ones((9, 8))"), "dt": ("real", "0.01"),
                     "h": ("real", "0.1")}),
    "massspring.System": ("km.massspring.System({x}, {springs}, stiffness={stiffness}, mass={mass}, "
                          "damping={damping}, gravity={gravity}).step({dt}, steps={steps})",
                          {"x": ("array", "MS_X"), "springs": ("index", "[[0, 1], [1, 2]]"),
                           "stiffness": ("real", "100.0"), "mass": ("real", "1.0"), "damping": ("real", "0.0"),
                           "gravity": ("vector", "[0.0, -9.8, 0.0]"), "dt": ("real", "0.01"),
                           "steps": ("count", "1")}),
    "massspring.cloth": ("km.massspring.cloth({nx}, {ny}, {size})",
                         {"nx": ("count", "4"), "ny": ("count", "4"), "size": ("real", "1.0")}),
    "fem.Body": ("km.fem.Body({vertices}, {elements}, youngs_modulus={E}, poisson_ratio={nu}, density={rho})"
                 ".step({dt}, max_newton={max_newton})",
                 {"vertices": ("array", "FEM_V"), "elements": ("index", "FEM_E"), "E": ("real", "1e5"),
                  "nu": ("real", "0.3"), "rho": ("real", "1000.0"), "dt": ("real", "0.01"),
                  "max_newton": ("count", "20")}),
    "fem.solve_static": ("km.fem.Body(FEM_V, FEM_E, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3, "
                         "fixed=[0, 1, 2], gravity=[0, -9.8]).solve_static(tol={tol}, max_iter={max_iter}, "
                         "load_steps={load_steps})",
                         {"tol": ("real", "1e-8"), "max_iter": ("count", "50"), "load_steps": ("count", "1")}),
    "fem.rectangle_mesh": ("km.fem.rectangle_mesh({lower}, {upper}, {n})",
                           {"lower": ("vector", "[0.0, 0.0]"), "upper": ("vector", "[1.0, 1.0]"),
                            "n": ("vector", "(2, 2)")}),
    "fem.box_mesh": ("km.fem.box_mesh([0, 0, 0], [1, 1, 1], {n})", {"n": ("count", "2")}),
    "fem.lame": ("km.fem.lame({E}, {nu})", {"E": ("real", "1e5"), "nu": ("real", "0.3")}),
    "fem.psi": ("km.fem.psi({F}, 'neohookean', {mu}, {lam})",
                {"F": ("array", "np.eye(3)[None] * 1.1"), "mu": ("real", "1.0"), "lam": ("real", "1.0")}),
    "sph.Fluid": ("km.sph.Fluid({positions}, {spacing}, rho0={rho0}, gravity=[0, -9.8], "
                  "domain=([0, 0], [0.2, 0.2])).step({dt})",
                  {"positions": ("array", "SPH_X + 0.01"), "spacing": ("real", "0.02"), "rho0": ("real", "1000.0"),
                   "dt": ("real", "1e-4")}),
    "sph.neighbor_pairs": ("km.sph.neighbor_pairs({points}, {radius})",
                           {"points": ("array", "rng.random((30, 2))"), "radius": ("real", "0.2")}),
    "sph.kernel": ("km.sph.kernel({r}, {h}, {d})",
                   {"r": ("array", "np.linspace(0, 1, 5)"), "h": ("real", "0.5"), "d": ("count", "2")}),
    "sph.block": ("km.sph.block({lower}, {upper}, {spacing})",
                  {"lower": ("vector", "[0.0, 0.0]"), "upper": ("vector", "[0.1, 0.1]"), "spacing": ("real", "0.02")}),
    "render.Camera": ("km.render.Scene().preview(km.render.Camera([0, 0, 5], [0, 0, 0], vfov={vfov}, "
                      "width={width}, height={height}))",
                      {"vfov": ("real", "40.0"), "width": ("count", "16"), "height": ("count", "12")}),
    "render.add_spheres": ("_s = km.render.Scene(); _s.add_spheres({centers}, {radii}, km.render.lambertian()); "
                           "_s.render(CAM, spp={spp})",
                           {"centers": ("array", "[[0.0, 0.0, 0.0]]"), "radii": ("array", "[1.0]"),
                            "spp": ("count", "2")}),
    "vortex.VortexParticles": ("km.vortex.VortexParticles({x}, {circulation}, {core}).step({dt})",
                               {"x": ("array", "rng.random((10, 2))"), "circulation": ("array", "np.ones(10)"),
                                "core": ("real", "0.05"), "dt": ("real", "0.01")}),
    "set_num_threads": ("km.set_num_threads({n}); km.poisson.solve(np.ones((64, 64)), 1/64)",
                        {"n": ("count", "2")}),
}

# Whole scenarios: degenerate-but-legal inputs, NaN written into views, copies, absurd sizes.
SCENARIOS = {
    "massspring.no_springs.energy": "km.massspring.System(MS_X, np.zeros((0, 2), int), stiffness=1.0).energy()",
    "massspring.zero_stiffness": ("_s = km.massspring.System(MS_X, [[0, 1]], stiffness=0.0); _s.step(0.01); "
                                  "assert _s.explicit_dt_limit == float('inf'); _s.energy()"),
    "massspring.no_springs.symplectic": ("_s = km.massspring.System(MS_X, np.zeros((0, 2), int), stiffness=1.0, "
                                         "gravity=[0, -9.8, 0]); _s.step(0.01, 'symplectic'); _s.x"),
    "sparse.tiny_diagonal": "km.sparse.cholesky(__import__('scipy.sparse').sparse.diags([1e-300] * 4).tocsr()).solve(np.ones(4))",
    "sparse.cg.tiny_diagonal": "km.sparse.cg(__import__('scipy.sparse').sparse.diags([1e-300] * 4).tocsr(), np.ones(4))",
    "render.empty_scene": "km.render.Scene().render(CAM, spp=2)",
    "render.empty_preview": "km.render.Scene().preview(CAM)",
    "fmm.cluster_far": ("km.fmm.laplace2d(np.vstack([rng.random((200, 2)) * 1e-9, [[1e3, 1e3], [-1e3, 5.0]]]), "
                        "np.ones(202))"),
    "fmm.scalar_charge": "km.fmm.laplace2d(rng.random((20, 2)), 1.0)",
    "fmm.overflow": "km.fmm.laplace2d(np.array([[0.0, 0.0], [1e308, 1e308]]), np.ones(2))",
    "poisson.overflow": "km.poisson.solve(np.full((8, 8), 1e308), 1/8)",
    "poisson.tiny_h": "km.poisson.solve(np.ones((8, 8)), 1e-308)",
    "sparse.overflow": "km.sparse.cg(SPD * 1e308, np.ones(16))",
    "grid.advect.overflow": "km.grid.advect(np.ones((8, 8)), (np.full((9, 8), 1e308), np.zeros((8, 9))), 1e10, 0.1)",
    "fem.psi.overflow": "km.fem.psi(np.eye(3)[None] * 1e200, 'neohookean', 1.0, 1.0)",
    "fem.rectangle_mesh.overflow": "km.fem.rectangle_mesh([0, 0], [1e308, 1e308], (2, 2))",
    "grid.nan_view.velocity_at": "_g = km.grid.Fluid((8, 8), 0.1); _g.u[3, 3] = np.nan; _g.velocity_at([[0.4, 0.4]])",
    "grid.nan_view.divergence": "_g = km.grid.Fluid((8, 8), 0.1); _g.u[3, 3] = np.nan; _g.divergence()",
    "grid.nan_view.kinetic_energy": "_g = km.grid.Fluid((8, 8), 0.1); _g.u[3, 3] = np.nan; _g.kinetic_energy()",
    "massspring.nan_view.energy": "_s = km.massspring.System(MS_X, [[0, 1]], stiffness=1.0); _s.x[0, 0] = np.nan; _s.energy()",
    "fem.nan_view.energy": ("_b = km.fem.Body(FEM_V, FEM_E, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3); "
                            "_b.x[0, 0] = np.nan; _b.energy()"),
    "sph.nan_view.kinetic_energy": "_f = km.sph.Fluid(SPH_X, 0.02); _f.v[0, 0] = np.nan; _f.kinetic_energy()",
    "sph.ids_garbage": "_f = km.sph.Fluid(SPH_X, 0.02); _f.ids[:] = 7; _f.step(1e-4)",
    "grid.periodic_gravity": ("_g = km.grid.Fluid((8, 8), 0.1, boundary='periodic', gravity=[1, 0]); _g.step(0.05); "
                              "assert np.allclose(_g.u, 0.05, atol=1e-8), _g.u; _g.u"),
    "grid.denormal_h": "km.grid.Fluid((8, 8), 5e-324).step(0.01)",
    "grid.huge_dt": "_g = km.grid.Fluid((8, 8), 0.1, gravity=[0, -9.8]); _g.step(1e300)",
    "sph.denormal_spacing": "km.sph.Fluid(SPH_X, 5e-324)",
    "sph.neighbor_pairs.denormal_cluster": "km.sph.neighbor_pairs(rng.random((50, 2)) * 5e-324, 5e-324)",
    "fem.rectangle_mesh.int32": "km.fem.rectangle_mesh([0, 0], [1, 1], (2**31, 2))",
    "fem.box_mesh.huge": "km.fem.box_mesh([0, 0, 0], [1, 1, 1], 2**31)",
    "diffusion.steps.huge": "km.diffusion.step(np.ones((8, 8)), 1.0, 1e-3, 0.1, steps=2**31)",
    "fem.load_steps.huge": ("km.fem.Body(FEM_V, FEM_E, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3, fixed=[0, 1, 2], "
                            "gravity=[0, -9.8]).solve_static(load_steps=2**40)"),
    "render.spp.huge": "_s = km.render.Scene(); _s.add_spheres([[0, 0, 0]], [1.0], km.render.lambertian()); _s.render(CAM, spp=2**40)",
    "sph.neighbor_pairs.far": "km.sph.neighbor_pairs([[-1e308, 0], [1e308, 0]], 1.0)",
    "render.preview.huge": "km.render.Scene().preview(km.render.Camera([0, 0, 5], [0, 0, 0], width=20000, height=15000))",
    "set_num_threads.huge": "km.set_num_threads(100000); km.poisson.solve(np.ones((64, 64)), 1/64)",
    "set_num_threads.int_max": "km.set_num_threads(2**31 - 1)",
    "copy.grid": "__import__('copy').copy(km.grid.Fluid((8, 8), 0.1))",
    "deepcopy.massspring": "__import__('copy').deepcopy(km.massspring.System(MS_X, [[0, 1]], stiffness=1.0))",
    "fmm.max_iter.huge": "km.poisson.solve(np.ones((8, 8)), 1/8, max_iter=2**63)",
    "poisson.shift.complex": "km.poisson.Solver((8, 8), 0.1, shift=1j)",
    "grid.complex_gravity": "km.grid.Fluid((8, 8), 0.1, gravity=[1j, 0])",
}

# Cases that must answer Ctrl-C (the runner sends SIGINT after this many seconds) when they do
# not finish or refuse by themselves.
INTERRUPTIBLE = {"diffusion.steps.huge", "fem.load_steps.huge", "render.spp.huge", "sph.neighbor_pairs.far",
                 "render.preview.huge", "fem.box_mesh.huge"}

VALUES = {"real": lambda base: REAL, "count": lambda base: COUNT, "name": lambda base: NAME,
          "vector": lambda base: VECTOR, "array": array_values, "index": index_values}


def cases():
    """Every case, in a fixed order; about one in six is in the fast subset."""
    out = []
    for entry, (template, args) in ENTRIES.items():
        base = {k: src for k, (_, src) in args.items()}
        out.append(dict(id=f"{entry}.base", setup=SETUP, expr=template.format(**base), arg=None,
                        interrupt=None, fast=True))
        for name, (kind, src) in args.items():
            for i, value in enumerate(VALUES[kind](src)):
                call = template.format(**{**base, name: value})
                out.append(dict(id=f"{entry}[{name}={value}]", setup=SETUP, expr=call, arg=name,
                                interrupt=None, fast=i < 2))
    for sid, expr in SCENARIOS.items():
        out.append(dict(id=sid, setup=SETUP, expr=expr, arg=None,
                        interrupt=3.0 if sid in INTERRUPTIBLE else None, fast=True))
    return out
