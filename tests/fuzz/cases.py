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
TMP = __import__('tempfile').mkdtemp()
P = __import__('pathlib').Path
WRITE = lambda f, d: P(f).write_bytes(d) if isinstance(d, bytes) else P(f).write_text(d)
RB = lambda f: P(f).read_bytes()
MPM_X = km.mpm.block([0.2, 0.2], [0.4, 0.4], 0.05)
NB_X, NB_V, NB_M = km.nbody.plummer(20, seed=1)
VR_X, VR_A = km.vortex.ring(1.0, 0.3, 1.0, 16)
TET_V, TET_E = km.fem.box_mesh([0, 0, 0], [1, 1, 1], 1)
BALL = km.mpm.sphere([0.0, 0.0, 0.0], 0.3, 0.05)
"""

# Simulation objects built in one statement, for scenarios
MPM_SIM = ("_m = km.mpm.Simulation((16, 16), 1/16); "
           "_m.add_particles(MPM_X, 'elastic', density=1000.0, youngs_modulus=1e4, poisson_ratio=0.3); ")
NB_SYS = "_n = km.nbody.System(NB_X, NB_V, NB_M, softening=0.05); "
VX_SYS = "_w = km.vortex.VortexParticles3D(VR_X, VR_A, 0.3); "
CONTACT = ("_c = km.contact.Scene(gravity=[0, -9.81, 0]); "
           "_c.add_solid(TET_V + [0.0, 0.05, 0.0], TET_E, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0); "
           "_c.add_collider('plane', point=[0.0, 0.0, 0.0], normal=[0.0, 1.0, 0.0]); ")
DIFF = "_d = km.massspring.System(MS_X, [[0, 1], [1, 2]], stiffness=100.0, gravity=[0, -9.8, 0]); "
TORCH = "_t = __import__('torch'); "

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

# The modules added later (mpm, 3D fmm, nbody, vortex 3D, mesh, io, surface); only their base
# call and first value per argument are in the fast subset.
NEW_ENTRIES = {
    "mpm.Simulation": ("km.mpm.Simulation({shape}, {h}, gravity={gravity}, friction={friction}, "
                       "max_cells_per_step={mcs}, max_dt={max_dt}).stable_dt()",
                       {"shape": ("vector", "(16, 16)"), "h": ("real", "1/16"), "gravity": ("vector", "[0.0, -9.8]"),
                        "friction": ("real", "0.0"), "mcs": ("real", "2.0"), "max_dt": ("real", "1e-2")}),
    "mpm.add_particles": ("_m = km.mpm.Simulation((16, 16), 1/16); _m.add_particles({positions}, {material}, "
                          "density={density}, youngs_modulus={E}, poisson_ratio={nu}, velocity={velocity}, "
                          "volume={volume}, cohesion={cohesion}); _m.step(1e-4); _m.x",
                          {"positions": ("array", "MPM_X"), "material": ("name", "'elastic'"),
                           "density": ("real", "1000.0"), "E": ("real", "1e4"), "nu": ("real", "0.3"),
                           "velocity": ("array", "[0.0, 0.0]"), "volume": ("real", "None"),
                           "cohesion": ("real", "0.0")}),
    "mpm.add_collider": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                         "_m.add_particles(MPM_X, 'elastic', density=1000.0); "
                         "_m.add_collider({{'shape': 'sphere', 'center': {center}, 'radius': {radius}}}, "
                         "boundary={boundary}, friction={friction}); _m.step(1e-4); _m.x",
                         {"center": ("vector", "[0.5, 0.2]"), "radius": ("real", "0.1"),
                          "boundary": ("name", "'slip'"), "friction": ("real", "0.0")}),
    "mpm.step": (MPM_SIM + "_m.step({dt}); _m.x", {"dt": ("real", "1e-4")}),
    "mpm.advance": (MPM_SIM + "_m.advance({duration}, cfl={cfl}); _m.x",
                    {"duration": ("real", "1e-3"), "cfl": ("real", "0.5")}),
    "mpm.stable_dt": (MPM_SIM + "_m.stable_dt({cfl})", {"cfl": ("real", "0.5")}),
    "fmm.laplace3d": ("km.fmm.laplace3d({sources}, {charges}, {targets}, eps={eps}, order={order}, "
                      "leaf_size={leaf_size})",
                      {"sources": ("array", "rng.random((40, 3))"), "charges": ("array", "np.ones(40)"),
                       "targets": ("array", "rng.random((5, 3))"), "eps": ("real", "1e-6"),
                       "order": ("count", "None"), "leaf_size": ("count", "None")}),
    "fmm.direct3d": ("km.fmm.direct3d({sources}, {charges}, gradient=True)",
                     {"sources": ("array", "rng.random((20, 3))"), "charges": ("array", "np.ones(20)")}),
    "nbody.System": ("_n = km.nbody.System({x}, {v}, {mass}, G={G}, softening={softening}, eps={eps}); "
                     "_n.step({dt}); (_n.x, _n.energy())",
                     {"x": ("array", "NB_X"), "v": ("array", "NB_V"), "mass": ("array", "NB_M"),
                      "G": ("real", "1.0"), "softening": ("real", "0.05"), "eps": ("real", "1e-8"),
                      "dt": ("real", "1e-3")}),
    "nbody.advance": (NB_SYS + "_n.advance({duration}, {dt}); _n.x",
                      {"duration": ("real", "3e-3"), "dt": ("real", "1e-3")}),
    "nbody.plummer": ("km.nbody.plummer({n}, seed={seed}, G={G}, total_mass={M}, scale={scale})",
                      {"n": ("count", "20"), "seed": ("count", "0"), "G": ("real", "1.0"), "M": ("real", "1.0"),
                       "scale": ("real", "1.0")}),
    "vortex.VortexParticles3D": ("_w = km.vortex.VortexParticles3D({x}, {strength}, {core}, eps={eps}); "
                                 "_w.step({dt}); (_w.x, _w.strength)",
                                 {"x": ("array", "VR_X"), "strength": ("array", "VR_A"), "core": ("real", "0.3"),
                                  "eps": ("real", "1e-10"), "dt": ("real", "1e-2")}),
    "vortex.VortexParticles3D.velocity": (VX_SYS + "_w.velocity({points})",
                                          {"points": ("array", "rng.random((4, 3))")}),
    "vortex.VortexParticles.velocity": ("km.vortex.VortexParticles(rng.random((10, 2)), np.ones(10), 0.05)"
                                        ".velocity({points})",
                                        {"points": ("array", "rng.random((4, 2))")}),
    "vortex.VortexParticles3D.advance": (VX_SYS + "_w.advance({duration}, {dt}); _w.x",
                                         {"duration": ("real", "2e-2"), "dt": ("real", "1e-2")}),
    "vortex.ring": ("km.vortex.ring({radius}, {core}, {circulation}, {n}, center={center}, axis={axis})",
                    {"radius": ("real", "1.0"), "core": ("real", "0.3"), "circulation": ("real", "1.0"),
                     "n": ("count", "16"), "center": ("vector", "[0.0, 0.0, 0.0]"),
                     "axis": ("vector", "[0.0, 0.0, 1.0]")}),
    "vortex.thick_ring": ("km.vortex.thick_ring({radius}, {core}, {circulation}, {n}, layers={layers}, "
                          "center={center}, axis={axis})",
                          {"radius": ("real", "1.0"), "core": ("real", "0.3"), "circulation": ("real", "1.0"),
                           "n": ("count", "8"), "layers": ("count", "3"),
                           "center": ("vector", "[0.0, 0.0, 0.0]"), "axis": ("vector", "[0.0, 0.0, 1.0]")}),
    "mesh.orient": ("km.mesh.orient({vertices}, {elements})",
                    {"vertices": ("array", "TET_V"), "elements": ("index", "TET_E")}),
    "mesh.remove_slivers": ("km.mesh.remove_slivers({vertices}, {elements}, min_quality={q})",
                            {"vertices": ("array", "TET_V"), "elements": ("index", "TET_E"), "q": ("real", "0.1")}),
    "mesh.clean": ("km.mesh.clean({vertices}, {elements}, min_quality={q}, drop_unused=True)",
                   {"vertices": ("array", "TET_V"), "elements": ("index", "TET_E"), "q": ("real", "0.1")}),
    "mesh.surface": ("km.mesh.surface({vertices}, {elements})",
                     {"vertices": ("array", "TET_V"), "elements": ("index", "TET_E")}),
    "io.write_particles": ("str(km.io.write_particles({path}, {points}, {{'a': {data}}}, ids={ids}))",
                           {"path": ("name", "TMP + '/p.vtu'"), "points": ("array", "rng.random((6, 3))"),
                            "data": ("array", "np.ones(6)"), "ids": ("index", "np.arange(6)")}),
    "io.write_mesh": ("str(km.io.write_mesh(TMP + '/m.vtu', {points}, {cells}, {{'a': {data}}}))",
                      {"points": ("array", "TET_V"), "cells": ("index", "TET_E"),
                       "data": ("array", "np.ones(len(TET_V))")}),
    "io.write_grid": ("km.io.read_vtk(km.io.write_grid(TMP + '/g.vti', {{'a': {field}}}, {h}, origin={origin}))",
                      {"field": ("array", "np.ones((4, 5, 6))"), "h": ("real", "0.1"),
                       "origin": ("vector", "(0.0, 0.0, 0.0)")}),
    "io.Series": ("_s = km.io.Series(TMP + '/s.pvd'); _s.add({time}, TMP + '/f.vtu'); _s.entries",
                  {"time": ("real", "0.5")}),
    "surface.reconstruct": ("km.surface.reconstruct({points}, {spacing}, method={method}, cell={cell}, "
                            "iso={iso}, smoothing={smoothing}).vertices",
                            {"points": ("array", "BALL"), "spacing": ("real", "0.05"),
                             "method": ("name", "'marching_cubes'"), "cell": ("real", "None"),
                             "iso": ("real", "None"), "smoothing": ("real", "None")}),
}

# km.contact, km.diff, km.torch and the viewer's splatter (added after the first fuzz rounds).
NEW_ENTRIES.update({
    "contact.Scene": ("_c = km.contact.Scene(gravity={gravity}, dhat={dhat}, friction={friction}, "
                      "friction_velocity={fv}); _c.add_solid(TET_V + [0.0, 0.05, 0.0], TET_E, youngs_modulus=1e5, "
                      "poisson_ratio=0.3, density=1000.0); _c.add_collider('plane'); _c.step(1e-2); _c.x",
                      {"gravity": ("vector", "[0.0, -9.81, 0.0]"), "dhat": ("real", "1e-3"),
                       "friction": ("real", "0.3"), "fv": ("real", "1e-3")}),
    "contact.add_solid": ("_c = km.contact.Scene(); _c.add_solid({vertices}, {tets}, youngs_modulus={E}, "
                          "poisson_ratio={nu}, density={rho}); _c.step(1e-2); _c.x",
                          {"vertices": ("array", "TET_V"), "tets": ("index", "TET_E"), "E": ("real", "1e5"),
                           "nu": ("real", "0.3"), "rho": ("real", "1000.0")}),
    "contact.add_collider.plane": (CONTACT.replace("_c.add_collider('plane', point=[0.0, 0.0, 0.0], "
                                                   "normal=[0.0, 1.0, 0.0]); ", "")
                                   + "_c.add_collider('plane', point={point}, normal={normal}); _c.step(1e-2); _c.x",
                                   {"point": ("vector", "[0.0, 0.0, 0.0]"), "normal": ("vector", "[0.0, 1.0, 0.0]")}),
    "contact.add_collider.sphere": ("_c = km.contact.Scene(); _c.add_solid(TET_V + [0.0, 2.0, 0.0], TET_E, "
                                    "youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0); "
                                    "_c.add_collider('sphere', center={center}, radius={radius}); _c.step(1e-2); _c.x",
                                    {"center": ("vector", "[0.0, -1.0, 0.0]"), "radius": ("real", "1.0")}),
    "contact.step": (CONTACT + "_c.step({dt}); (_c.x, _c.min_distance(radius=10.0))", {"dt": ("real", "1e-2")}),
    "contact.advance": (CONTACT + "_c.advance({duration}, {dt}); _c.x",
                        {"duration": ("real", "2e-2"), "dt": ("real", "1e-2")}),
    "diff.rollout": (DIFF + "_r = km.diff.rollout(_d, {steps}, {dt}, wrt={wrt}, checkpoints={checkpoints}, "
                     "integrator={integrator}); _r.backward({{'x': np.ones((3, 3))}})",
                     {"steps": ("count", "4"), "dt": ("real", "1e-2"), "wrt": ("name", "('x', 'v', 'stiffness')"),
                      "checkpoints": ("count", "None"), "integrator": ("name", "'symplectic'")}),
    "diff.controls": (DIFF + "_r = km.diff.rollout(_d, 4, 1e-2, wrt=('controls',), controls={controls}, "
                      "integrator='implicit'); _r.backward({{'v': np.ones((3, 3))}})",
                      {"controls": ("array", "np.zeros((4, 3, 3))")}),
    "diff.backward": (DIFF + "_r = km.diff.rollout(_d, 3, 1e-2, wrt=('x', 'mass')); _r.backward({{'x': {g}}})",
                      {"g": ("array", "np.ones((3, 3))")}),
    "torch.rollout": (DIFF + TORCH + "_x = _t.tensor(MS_X, requires_grad=True); "
                      "_o = km.torch.rollout(_d, {steps}, {dt}, {{'x': _x}}, integrator='symplectic'); "
                      "_o['x'].sum().backward(); _x.grad.numpy()",
                      {"steps": ("count", "3"), "dt": ("real", "1e-2")}),
    # depth is inf where no sphere is hit (the documented sentinel): the ids and the hit count
    "render.splat_spheres": ("km.render.splat_spheres(CAM, {centers}, {radii})[2:]",
                             {"centers": ("array", "rng.random((50, 3))"), "radii": ("real", "0.1")}),
})

NEW_SCENARIOS = {
    "mpm.nan_view.x.step": MPM_SIM + "_m.x[0, 0] = np.nan; _m.step(1e-4); _m.x",
    "mpm.nan_view.v.stable_dt": MPM_SIM + "_m.v[0, 0] = np.nan; _m.stable_dt()",
    "mpm.nan_view.v.kinetic_energy": MPM_SIM + "_m.v[0, 0] = np.nan; _m.kinetic_energy()",
    "mpm.inf_view.F.step": MPM_SIM + "_m.F[0] = np.inf; _m.step(1e-4); _m.x",
    "mpm.huge_view.x.step": MPM_SIM + "_m.x[0] = 1e308; _m.step(1e-4); _m.x",
    "mpm.huge_view.v.step": MPM_SIM + "_m.v[:] = 1e300; _m.step(1e-4); _m.x",
    "mpm.zero_mass.step": MPM_SIM + "_m.mass[:] = 0.0; _m.step(1e-4); _m.x",
    "mpm.negative_mass.step": MPM_SIM + "_m.mass[:] = -1.0; _m.step(1e-4); _m.x",
    "mpm.nan_volume.step": MPM_SIM + "_m.volume[0] = np.nan; _m.step(1e-4); _m.x",
    "mpm.zero_F.step": MPM_SIM + "_m.F[:] = 0.0; _m.step(1e-4); _m.x",
    "mpm.material_view.garbage": MPM_SIM + "_m.material[:] = 99; _m.step(1e-4); _m.x",
    "mpm.Jp_view.negative": MPM_SIM + "_m.Jp[:] = -1.0; _m.step(1e-4); _m.x",
    "mpm.time.nan": MPM_SIM + "_m.time = float('nan'); _m.step(1e-4); _m.time",
    "mpm.set_state.nan": MPM_SIM + "_st = _m.state(); _st['x'][0, 0] = np.nan; _m.set_state(_st); _m.x",
    "mpm.set_state.complex": MPM_SIM + "_st = _m.state(); _st['v'] = _st['v'] + 1j; _m.set_state(_st); _m.v",
    "mpm.set_state.missing": MPM_SIM + "_m.set_state({'x': _m.x.copy()})",
    "mpm.set_state.wrong_shape": MPM_SIM + "_st = _m.state(); _st['x'] = _st['x'][:1]; _m.set_state(_st)",
    "mpm.set_state.strings": MPM_SIM + "_st = _m.state(); _st['mass'] = np.array(['a'] * len(_st['mass'])); _m.set_state(_st)",
    "mpm.set_state.material_float": MPM_SIM + "_st = _m.state(); _st['material'] = _st['material'] + 0.5; _m.set_state(_st); _m.material",
    "mpm.set_state.time_str": MPM_SIM + "_st = _m.state(); _st['time'] = 'x'; _m.set_state(_st)",
    "mpm.set_state.steps_huge": MPM_SIM + "_st = _m.state(); _st['steps'] = 2**70; _m.set_state(_st)",
    "mpm.set_state.not_dict": MPM_SIM + "_m.set_state(None)",
    "mpm.set_state.rollback": (MPM_SIM + "_x0 = _m.x.copy(); _st = _m.state(); _st['Jp'] = _st['Jp'] * np.nan; "
                               "_ok = False\ntry:\n    _m.set_state(_st)\nexcept ValueError:\n    _ok = True\n"
                               "assert _ok and np.isfinite(_m.Jp).all(); _m.Jp"),
    "mpm.advance.huge": MPM_SIM + "_m.advance(1e300)",
    "mpm.no_particles.step": "_m = km.mpm.Simulation((16, 16), 1/16); _m.step(1e-3); _m.kinetic_energy()",
    "mpm.no_particles.stable_dt": "km.mpm.Simulation((16, 16), 1/16).stable_dt()",
    "mpm.huge_grid": "km.mpm.Simulation((2**40, 2**40), 1.0)",
    "mpm.denormal_h": "km.mpm.Simulation((16, 16), 5e-324).stable_dt()",
    "mpm.huge_h": "km.mpm.Simulation((16, 16), 1e300).stable_dt()",
    "mpm.particles_outside": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                              "_m.add_particles(MPM_X + 100.0, 'elastic', density=1000.0); _m.step(1e-4); _m.x"),
    "mpm.sand_no_angle": "_m = km.mpm.Simulation((16, 16), 1/16); _m.add_particles(MPM_X, 'sand', density=1000.0)",
    "mpm.sand_angle_huge": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                            "_m.add_particles(MPM_X, 'sand', density=1000.0, friction_angle=1e300); _m.step(1e-4); _m.x"),
    "mpm.nu_half": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                    "_m.add_particles(MPM_X, 'elastic', density=1000.0, poisson_ratio=0.5); _m.step(1e-4); _m.x"),
    "mpm.nu_nan": "_m = km.mpm.Simulation((16, 16), 1/16); _m.add_particles(MPM_X, 'elastic', density=1000.0, poisson_ratio=float('nan'))",
    "mpm.nu_str": "_m = km.mpm.Simulation((16, 16), 1/16); _m.add_particles(MPM_X, 'elastic', density=1000.0, poisson_ratio='x')",
    "mpm.volume_array_bad": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                             "_m.add_particles(MPM_X, 'elastic', density=1000.0, volume=-np.ones(len(MPM_X))); _m.step(1e-4); _m.x"),
    "mpm.collider_box_bad": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                             "_m.add_collider({'shape': 'box', 'lower': [0.5], 'upper': [0.2, 0.2]})"),
    "mpm.collider_box_nan": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                             "_m.add_collider({'shape': 'box', 'lower': [np.nan, 0], 'upper': [0.2, 0.2]})"),
    "mpm.collider_not_dict": "_m = km.mpm.Simulation((16, 16), 1/16); _m.add_collider([1, 2])",
    "mpm.collider_shape_unhashable": "_m = km.mpm.Simulation((16, 16), 1/16); _m.add_collider({'shape': ['box']})",
    "mpm.collider_center_3": ("_m = km.mpm.Simulation((16, 16), 1/16); "
                              "_m.add_collider({'shape': 'sphere', 'center': [0.5, 0.5, 0.5], 'radius': 0.1})"),
    "mpm.3d.base": ("_m = km.mpm.Simulation((8, 8, 8), 1/8); "
                    "_m.add_particles(km.mpm.block([0.3] * 3, [0.5] * 3, 1/16), 'water', density=1000.0); "
                    "_m.step(1e-4); _m.x"),
    "mpm.copy": "__import__('copy').copy(km.mpm.Simulation((16, 16), 1/16))",
    "mpm.block.denormal": "km.mpm.block([0, 0], [1, 1], 5e-324)",
    "mpm.sphere.huge": "km.mpm.sphere([0, 0, 0], 1e300, 1.0)",
    "fmm3d.cluster_far": ("km.fmm.laplace3d(np.vstack([rng.random((300, 3)) * 1e-9, [[1e3, 1e3, 1e3], [-1e3, 5, 0]]]), "
                          "np.ones(302), order=6)"),
    "fmm3d.scalar_charge": "km.fmm.laplace3d(rng.random((20, 3)), 1.0)",
    "fmm3d.overflow": "km.fmm.laplace3d(np.array([[0.0, 0, 0], [1e308, 1e308, 1e308]]), np.ones(2))",
    "fmm3d.overflow.fmm": "km.fmm.laplace3d(np.vstack([rng.random((50, 3)), [[1e308, 1e308, 1e308]]]), np.ones(51), order=4)",
    "fmm3d.coincident": "km.fmm.laplace3d(np.zeros((30, 3)), np.ones(30), order=4)",
    "fmm3d.tiny_charges": "km.fmm.laplace3d(rng.random((30, 3)), np.full(30, 5e-324), order=4)",
    "fmm3d.huge_charges": "km.fmm.laplace3d(rng.random((30, 3)), np.full(30, 1e308))",
    "fmm3d.empty_sources": "km.fmm.laplace3d(np.zeros((0, 3)), np.zeros(0))",
    "fmm3d.empty_targets": "km.fmm.laplace3d(rng.random((5, 3)), np.ones(5), np.zeros((0, 3)))",
    "fmm3d.leaf_size.one": "km.fmm.laplace3d(rng.random((200, 3)), np.ones(200), leaf_size=1, order=3)",
    "fmm3d.leaf_size.huge": "km.fmm.laplace3d(rng.random((50, 3)), np.ones(50), leaf_size=2**62, order=3)",
    "fmm3d.denormal_cluster": "km.fmm.laplace3d(rng.random((100, 3)) * 5e-324, np.ones(100), order=4)",
    "nbody.coincident": "_n = km.nbody.System(np.zeros((4, 3)), np.zeros((4, 3)), 1.0); _n.step(1e-3)",
    "nbody.coincident.energy": "km.nbody.System(np.zeros((4, 3)), np.zeros((4, 3)), 1.0).energy()",
    "nbody.zero_mass.virial": "km.nbody.System(NB_X, NB_V, 0.0).virial_ratio()",
    "nbody.single.virial": "km.nbody.System([[0.0, 0, 0]], [[1.0, 0, 0]], 1.0).virial_ratio()",
    "nbody.huge_x.energy": "km.nbody.System(NB_X * 1e300, NB_V, NB_M).energy()",
    "nbody.huge_v.energy": "km.nbody.System(NB_X, NB_V * 1e300, NB_M).kinetic_energy()",
    "nbody.huge_mass.step": "_n = km.nbody.System(NB_X, NB_V, NB_M * 1e308); _n.step(1e-3); _n.x",
    "nbody.huge_G.energy": "km.nbody.System(NB_X, NB_V, NB_M, G=1e308).energy()",
    "nbody.huge_softening": "_n = km.nbody.System(NB_X, NB_V, NB_M, softening=1e300); _n.step(1e-3); _n.energy()",
    "nbody.denormal_softening": "_n = km.nbody.System(NB_X, NB_V, NB_M, softening=5e-324); _n.step(1e-3); _n.energy()",
    "nbody.nan_view.energy": NB_SYS + "_n.x[0, 0] = np.nan; _n.energy()",
    "nbody.nan_view.momentum": NB_SYS + "_n.v[0, 0] = np.nan; _n.momentum()",
    "nbody.nan_view.step": NB_SYS + "_n.v[0, 0] = np.nan; _n.step(1e-3); _n.x",
    "nbody.mass_view.nan": NB_SYS + "_n.mass[0] = np.nan; _n.step(1e-3); _n.x",
    "nbody.set_state.nan": NB_SYS + "_st = _n.state(); _st['x'][0, 0] = np.nan; _n.set_state(_st); _n.x",
    "nbody.set_state.missing": NB_SYS + "_n.set_state({'x': _n.x})",
    "nbody.set_state.not_dict": NB_SYS + "_n.set_state(3)",
    "nbody.set_state.time_nan": NB_SYS + "_st = _n.state(); _st['time'] = float('nan'); _n.set_state(_st); _n.time",
    "nbody.set_state.time_str": NB_SYS + "_st = _n.state(); _st['time'] = 'x'; _n.set_state(_st)",
    "nbody.set_state.steps_float": NB_SYS + "_st = _n.state(); _st['steps'] = float('inf'); _n.set_state(_st)",
    "nbody.set_state.a_shape": NB_SYS + "_n.step(1e-3); _st = _n.state(); _st['a'] = np.ones(2); _n.set_state(_st); _n.step(1e-3); _n.x",
    "nbody.set_state.a_nan": NB_SYS + "_n.step(1e-3); _st = _n.state(); _st['a'] = _st['a'] * np.nan; _n.set_state(_st); _n.step(1e-3); _n.x",
    "nbody.set_state.complex": NB_SYS + "_st = _n.state(); _st['v'] = _st['v'] + 1j; _n.set_state(_st); _n.v",
    "nbody.advance.huge": NB_SYS + "_n.advance(1e300, 1e-3)",
    "nbody.advance.dt_tiny": NB_SYS + "_n.advance(1.0, 1e-300)",
    "nbody.plummer.huge": "km.nbody.plummer(2**40)",
    "nbody.plummer.seed_bad": "km.nbody.plummer(20, seed='x')",
    "vortex3d.coincident": "_w = km.vortex.VortexParticles3D(np.zeros((5, 3)), np.ones((5, 3)), 0.1); _w.step(1e-2); _w.x",
    "vortex3d.huge_strength": "_w = km.vortex.VortexParticles3D(VR_X, VR_A * 1e300, 0.3); _w.step(1e-2); _w.x",
    "vortex3d.denormal_core": "_w = km.vortex.VortexParticles3D(VR_X, VR_A, 5e-324); _w.step(1e-2); _w.x",
    "vortex3d.huge_core": "_w = km.vortex.VortexParticles3D(VR_X, VR_A, 1e300); _w.step(1e-2); _w.x",
    "vortex3d.huge_x": "_w = km.vortex.VortexParticles3D(VR_X * 1e300, VR_A, 0.3); _w.velocity()",
    "vortex3d.nan_view.step": VX_SYS + "_w.strength[0, 0] = np.nan; _w.step(1e-2); _w.x",
    "vortex3d.nan_view.velocity": VX_SYS + "_w.x[0, 0] = np.nan; _w.velocity()",
    "vortex3d.nan_view.impulse": VX_SYS + "_w.x[0, 0] = np.nan; _w.linear_impulse()",
    "vortex3d.set_state.nan": VX_SYS + "_st = _w.state(); _st['x'][0, 0] = np.nan; _w.set_state(_st); _w.x",
    "vortex3d.set_state.missing": VX_SYS + "_w.set_state({})",
    "vortex3d.set_state.time_str": VX_SYS + "_st = _w.state(); _st['time'] = 'x'; _w.set_state(_st)",
    "vortex3d.advance.huge": VX_SYS + "_w.advance(1e300, 1e-2)",
    "vortex.ring.huge_n": "km.vortex.ring(1.0, 0.3, 1.0, 2**40)",
    "vortex.thick_ring.huge_layers": "km.vortex.thick_ring(1.0, 0.3, 1.0, 8, layers=2**31)",
    "vortex.thick_ring.huge_radius": "km.vortex.thick_ring(1e308, 0.3, 1.0, 8)",
    "vortex.ring.huge_circulation": "km.vortex.ring(1e308, 0.3, 1e308, 16)",
    "mesh.surface.empty": "km.mesh.surface(TET_V, np.zeros((0, 4), int))",
    "mesh.clean.empty": "km.mesh.clean(TET_V, np.zeros((0, 4), int), drop_unused=True)",
    "mesh.clean.huge": "km.mesh.clean(TET_V * 1e300, TET_E)",
    "mesh.orient.huge": "km.mesh.orient(TET_V * 1e300, TET_E)",
    "mesh.remove_slivers.huge": "km.mesh.remove_slivers(TET_V * 1e300, TET_E)",
    "mesh.orient.denormal": "km.mesh.orient(TET_V * 5e-324, TET_E)",
    "mesh.flat": "km.mesh.clean(TET_V * [1, 1, 0], TET_E)",
    "mesh.triangles": "km.mesh.surface(FEM_V, FEM_E)",
    "mesh.index_past_int64": "km.mesh.orient(TET_V, np.array([[0, 1, 2, 2**64 - 1]], dtype=np.uint64))",
    "mesh.index_object_huge": "km.mesh.orient(TET_V, [[0, 1, 2, 10**30]])",
    "io.write_particles.bad_dir": "km.io.write_particles('/proc/nonexistent/p.vtu', np.ones((3, 3)))",
    "io.write_particles.dir": "km.io.write_particles(TMP, np.ones((3, 3)))",
    "io.write_particles.path_none": "km.io.write_particles(None, np.ones((3, 3)))",
    "io.write_particles.data_not_dict": "km.io.write_particles(TMP + '/p.vtu', np.ones((3, 3)), [1, 2])",
    "io.write_particles.data_bad_name": "km.io.write_particles(TMP + '/p.vtu', np.ones((3, 3)), {3: np.ones(3)})",
    "io.write_particles.data_complex": "km.io.write_particles(TMP + '/p.ply', np.ones((3, 3)), {'a': np.ones(3) * 1j})",
    "io.write_particles.ids_huge": "km.io.write_particles(TMP + '/p.vtu', np.ones((3, 3)), ids=[0, 1, 2**62])",
    "io.write_particles.ids_neg": "km.io.write_particles(TMP + '/p.vtu', np.ones((3, 3)), ids=[0, 1, -1])",
    "io.write_particles.empty": "km.io.read_vtk(km.io.write_particles(TMP + '/e.vtu', np.zeros((0, 3))))",
    "io.write_particles.roundtrip": ("_p = rng.random((5, 3)); _r = km.io.read_vtk(km.io.write_particles(TMP + '/r.vtu', _p, "
                                     "{'a': np.arange(5.0)})); assert np.array_equal(_r['points'], _p), _r; _r['points']"),
    "io.write_mesh.bad_cells_type": "km.io.write_mesh(TMP + '/m.vtu', TET_V, {'pyramid': TET_E})",
    "io.write_mesh.cells_index": "km.io.write_mesh(TMP + '/m.vtu', TET_V, TET_E + 100)",
    "io.write_mesh.cells_float": "km.io.write_mesh(TMP + '/m.vtu', TET_V, TET_E + 0.5)",
    "io.write_mesh.cells_list_bad": "km.io.write_mesh(TMP + '/m.vtu', TET_V, [('tetra',)])",
    "io.write_mesh.cell_data_len": "km.io.write_mesh(TMP + '/m.vtu', TET_V, TET_E, cell_data={'a': np.ones(1000)})",
    "io.write_mesh.obj_tets": "km.io.write_mesh(TMP + '/m.obj', TET_V, TET_E)",
    "io.write_grid.empty": "km.io.write_grid(TMP + '/g.vti', {}, 0.1)",
    "io.write_grid.not_dict": "km.io.write_grid(TMP + '/g.vti', np.ones((4, 4)), 0.1)",
    "io.write_grid.complex": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4)) * 1j}, 0.1)",
    "io.write_grid.strings": "km.io.write_grid(TMP + '/g.vti', {'a': np.array([['a']])}, 0.1)",
    "io.write_grid.nan": "km.io.read_vtk(km.io.write_grid(TMP + '/g.vti', {'a': np.full((4, 4), np.nan)}, 0.1))",
    "io.write_grid.1d": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones(4)}, 0.1)",
    "io.write_grid.vector_huge": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4, 4, 9))}, 0.1)",
    "io.write_grid.h_str": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4))}, 'x')",
    "io.write_grid.h_complex": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4))}, 1j)",
    "io.write_grid.origin_nan": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4))}, 0.1, origin=[np.nan, 0, 0])",
    "io.write_grid.origin_short": "km.io.write_grid(TMP + '/g.vti', {'a': np.ones((4, 4))}, 0.1, origin=[0])",
    "io.read_vtk.missing": "km.io.read_vtk(TMP + '/nope.vtu')",
    "io.read_vtk.empty_file": "WRITE(TMP + '/e2.vtu', ''); km.io.read_vtk(TMP + '/e2.vtu')",
    "io.read_vtk.garbage": "WRITE(TMP + '/g2.vtu', bytes(range(256))); km.io.read_vtk(TMP + '/g2.vtu')",
    "io.read_vtk.truncated": ("_f = km.io.write_particles(TMP + '/t.vtu', rng.random((50, 3))); _b = RB(_f); "
                              "WRITE(_f, _b[:len(_b) // 2]); km.io.read_vtk(_f)"),
    "io.read_vtk.bitflip": ("_f = km.io.write_particles(TMP + '/b.vtu', rng.random((50, 3))); _b = bytearray(RB(_f)); "
                            "_b[len(_b) // 2] ^= 0x55; WRITE(_f, bytes(_b)); km.io.read_vtk(_f)"),
    "io.read_vtk.wrong_xml": "WRITE(TMP + '/x.vtu', '<a><b/></a>'); km.io.read_vtk(TMP + '/x.vtu')",
    "io.read_vtk.dir": "km.io.read_vtk(TMP)",
    "io.read_vtk.none": "km.io.read_vtk(None)",
    "io.read_vtk.ply": "km.io.read_vtk(km.io.write_particles(TMP + '/q.ply', rng.random((5, 3))))",
    "io.Series.bad_suffix": "km.io.Series(TMP + '/s.txt')",
    "io.Series.resume_garbage": "WRITE(TMP + '/r.pvd', '<<<'); km.io.Series(TMP + '/r.pvd', resume=True)",
    "io.Series.resume_series_garbage": "WRITE(TMP + '/r.series', '[1]'); km.io.Series(TMP + '/r.series', resume=True)",
    "io.Series.resume_bad_time": ("WRITE(TMP + '/r2.series', '{\"files\": [{\"time\": \"x\", \"name\": \"a\"}]}'); "
                                  "km.io.Series(TMP + '/r2.series', resume=True)"),
    "io.Series.file_none": "km.io.Series(TMP + '/s.pvd').add(0.0, None)",
    "io.Series.unwritable": "km.io.Series('/proc/nonexistent/s.pvd').add(0.0, 'f.vtu')",
    "surface.empty": "km.surface.reconstruct(np.zeros((0, 3)), 0.05).vertices",
    "surface.one_point": "km.surface.reconstruct(np.zeros((1, 3)), 0.05).vertices",
    "surface.far_apart": "km.surface.reconstruct(np.array([[0.0, 0, 0], [1e6, 0, 0]]), 0.05).vertices",
    "surface.huge_extent": "km.surface.reconstruct(np.array([[0.0, 0, 0], [1e300, 0, 0]]), 0.05).vertices",
    "surface.denormal_spacing": "km.surface.reconstruct(BALL, 5e-324).vertices",
    "surface.huge_spacing": "km.surface.reconstruct(BALL, 1e300).vertices",
    "surface.tiny_cell": "km.surface.reconstruct(BALL, 0.05, cell=1e-9).vertices",
    "surface.iso_nan": "km.surface.reconstruct(BALL, 0.05, iso=float('nan')).vertices",
    "surface.iso_huge": "km.surface.reconstruct(BALL, 0.05, iso=1e300).vertices",
    "surface.splashsurf.iso_str": "km.surface.reconstruct(BALL, 0.05, method='splashsurf', iso='x').vertices",
    "surface.coincident": "km.surface.reconstruct(np.zeros((100, 3)), 0.05).vertices",
    "surface.area_finite": "_s = km.surface.reconstruct(BALL, 0.05); (_s.area, _s.volume)",
}
# A few of the scenarios above in the fast subset (about 2 s; the whole new fast part ~11 s).
NEW_FAST = {"mpm.nan_view.x.step", "mpm.set_state.rollback", "fmm3d.cluster_far", "nbody.set_state.nan",
            "vortex3d.nan_view.velocity", "mesh.orient.denormal", "io.read_vtk.truncated", "surface.iso_nan"}
NEW_INTERRUPTIBLE = {"mpm.advance.huge", "nbody.advance.huge", "nbody.advance.dt_tiny", "vortex3d.advance.huge",
                     "nbody.plummer.huge", "vortex.ring.huge_n", "vortex.thick_ring.huge_layers", "mpm.huge_grid",
                     "surface.tiny_cell", "surface.far_apart", "surface.huge_extent", "mpm.sphere.huge",
                     "mpm.block.denormal", "fmm3d.leaf_size.huge"}

NEW_SCENARIOS.update({
    "contact.start_intersecting": ("_c = km.contact.Scene(); _c.add_solid(TET_V, TET_E, youngs_modulus=1e5, "
                                   "poisson_ratio=0.3, density=1000.0); _c.add_solid(TET_V + 0.5, TET_E, "
                                   "youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0); _c.step(1e-2)"),
    "contact.nan_view.x": CONTACT + "_c.x[0, 0] = np.nan; _c.step(1e-2); _c.x",
    "contact.set_state.nan": CONTACT + "_st = _c.state(); _st['x'][0, 0] = np.nan; _c.set_state(_st); _c.x",
    "contact.huge_velocity": CONTACT + "_c.v = np.full_like(_c.v, 1e300); _c.step(1e-2); _c.x",
    "contact.copy": CONTACT + "__import__('copy').copy(_c)",
    "contact.advance.huge": CONTACT + "_c.advance(1e300, 1e-2)",
    "diff.rollout.not_a_sim": "km.diff.rollout(object(), 3, 1e-2, wrt=('x',))",
    "diff.rollout.steps_huge": DIFF + "km.diff.rollout(_d, 2**40, 1e-2, wrt=('x',), checkpoints=3)",
    "diff.backward.unknown_name": DIFF + "km.diff.rollout(_d, 2, 1e-2, wrt=('x',)).backward({'q': np.ones(3)})",
    "diff.backward.nan_state": (DIFF + "_d.x[0, 0] = np.nan; "
                                "km.diff.rollout(_d, 2, 1e-2, wrt=('x',)).backward({'x': np.ones((3, 3))})"),
    "torch.rollout.bad_input_name": DIFF + TORCH + "km.torch.rollout(_d, 2, 1e-2, {'nope': _t.ones(3)})",
    "torch.rollout.int_tensor": DIFF + TORCH + "km.torch.rollout(_d, 2, 1e-2, {'x': _t.ones((3, 3), dtype=_t.int64)})",
    "render.splat_spheres.huge_image": ("km.render.splat_spheres(km.render.Camera([0, 0, 5], [0, 0, 0], "
                                        "width=2**31, height=2**31), rng.random((5, 3)), 0.1)[2:]"),
    "render.splat_spheres.eye_inside": "km.render.splat_spheres(CAM, [[0.0, 0.0, 5.0]], 1.0)[2:]",
})
NEW_FAST |= {"contact.start_intersecting", "diff.backward.nan_state", "torch.rollout.int_tensor",
             "render.splat_spheres.eye_inside"}
NEW_INTERRUPTIBLE |= {"contact.advance.huge", "diff.rollout.steps_huge", "render.splat_spheres.huge_image"}

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


def _entry_cases(entries, n_fast, interrupt):
    """The base call of each entry point, and one case per bad value of each argument (the
    first ``n_fast`` values of each in the fast subset)."""
    out = []
    for entry, (template, args) in entries.items():
        base = {k: src for k, (_, src) in args.items()}
        out.append(dict(id=f"{entry}.base", setup=SETUP, expr=template.format(**base), arg=None,
                        interrupt=None, fast=True))
        for name, (kind, src) in args.items():
            for i, value in enumerate(VALUES[kind](src)):
                call = template.format(**{**base, name: value})
                out.append(dict(id=f"{entry}[{name}={value}]", setup=SETUP, expr=call, arg=name,
                                interrupt=interrupt, fast=i < n_fast))
    return out


def cases():
    """Every case, in a fixed order; about one in six is in the fast subset."""
    out = _entry_cases(ENTRIES, 2, None)
    for sid, expr in SCENARIOS.items():
        out.append(dict(id=sid, setup=SETUP, expr=expr, arg=None,
                        interrupt=3.0 if sid in INTERRUPTIBLE else None, fast=True))
    out += _entry_cases(NEW_ENTRIES, 1, 3.0)
    for sid, expr in NEW_SCENARIOS.items():
        out.append(dict(id=sid, setup=SETUP, expr=expr, arg=None,
                        interrupt=3.0 if sid in NEW_INTERRUPTIBLE else None, fast=sid in NEW_FAST))
    return out


# ------------------------------------------------------------------ colliders on one body, km.fem.Scene,
# km.contact.attach, and km.diff over km.grid and km.sph (added in the review round)
SETUP_BODIES = SETUP + """
CL = km.massspring.cloth(4, 4, 1.0, plane='xz', origin=(0.0, 0.5, 0.0))
CL2 = km.massspring.cloth(4, 4, 1.0, dim=2, origin=(0.0, 0.5))
"""
FEM3 = ("_b = km.fem.Body(TET_V * 0.1 + [0.0, 0.05, 0.0], TET_E, youngs_modulus=1e5, poisson_ratio=0.3, "
        "density=1000.0, gravity=[0, -9.81, 0]); ")
FEM2 = ("_b = km.fem.Body(FEM_V * 0.1 + [0.0, 0.05], FEM_E, youngs_modulus=1e5, poisson_ratio=0.3, "
        "density=1000.0, gravity=[0, -9.81]); ")
MS3 = "_s = km.massspring.System(CL.x, CL.springs, stiffness=100.0, mass=0.01, gravity=[0, -9.81, 0]); "
MS2 = "_s = km.massspring.System(CL2.x, CL2.springs, stiffness=100.0, mass=0.01, gravity=[0, -9.81]); "
GRID = "_g = km.grid.Fluid((8, 8), 1/8, tol=1e-8); _g.u[...] = 0.1; "
SMOKE = ("_g = km.grid.Fluid((8, 8), 1/8, tol=1e-8, density=True); _m = np.zeros((8, 8), bool); _m[3:5, :2] = True; "
         "_g.add_source(_m, density=1.0); ")
WSPH = "_f = km.sph.Fluid(SPH_X + 0.01, 0.02, method='wcsph', gravity=[0, -9.81], domain=([0, 0], [0.2, 0.2])); "

BODY_ENTRIES = {
    "fem.add_collider.plane": (FEM3 + "_b.add_collider('plane', point={point}, normal={normal}); "
                               "_b.step({dt}); _b.x",
                               {"point": ("vector", "[0.0, 0.0, 0.0]"), "normal": ("vector", "[0.0, 1.0, 0.0]"),
                                "dt": ("real", "1e-2")}),
    "fem.add_collider.sphere": (FEM3 + "_b.add_collider('sphere', center={center}, radius={radius}, "
                                "subdivisions={subdivisions}); _b.step(1e-2); _b.x",
                                {"center": ("vector", "[0.05, -1.0, 0.05]"), "radius": ("real", "1.0"),
                                 "subdivisions": ("count", "2")}),
    "fem.add_collider.box": (FEM3 + "_b.add_collider('box', lower={lower}, upper={upper}, velocity={velocity}); "
                             "_b.step(1e-2); _b.x",
                             {"lower": ("vector", "[-1.0, -1.0, -1.0]"), "upper": ("vector", "[1.0, 0.0, 1.0]"),
                              "velocity": ("vector", "[0.0, 0.1, 0.0]")}),
    "fem.add_collider.mesh": (FEM3 + "_b.add_collider('mesh', vertices={vertices}, triangles={triangles}); "
                              "_b.step(1e-2); _b.x",
                              {"vertices": ("array", "[[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]]"),
                               "triangles": ("index", "[[0, 2, 1]]")}),
    "fem.add_collider.motion": (FEM3 + "_b.add_collider('box', lower=[-1, -1, -1], upper=[1, 0, 1], "
                                "angular_velocity={angular_velocity}, motion={motion}); _b.step(1e-2); _b.x",
                                {"angular_velocity": ("vector", "None"), "motion": ("name", "None")}),
    "fem.add_collider.symplectic.2d": (FEM2 + "_b.add_collider({shape}, center=[0.05, -1.0], radius={radius}, "
                                       "friction={friction}); _b.step({dt}, 'symplectic'); _b.x",
                                       {"shape": ("name", "'sphere'"), "radius": ("real", "1.0"),
                                        "friction": ("real", "0.3"), "dt": ("real", "1e-5")}),
    "fem.add_collider.box.2d": (FEM2 + "_b.add_collider('box', lower={lower}, upper={upper}, velocity={velocity}); "
                                "_b.step(1e-5, 'symplectic'); _b.x",
                                {"lower": ("vector", "[-1.0, -1.0]"), "upper": ("vector", "[1.0, 0.0]"),
                                 "velocity": ("vector", "[0.0, 0.0]")}),
    "massspring.add_collider.sphere": (MS3 + "_s.add_collider('sphere', center={center}, radius={radius}); "
                                       "_s.step({dt}, {integrator}); _s.x",
                                       {"center": ("vector", "[0.5, 0.0, 0.5]"), "radius": ("real", "0.3"),
                                        "dt": ("real", "1e-2"), "integrator": ("name", "'implicit'")}),
    "massspring.add_collider.plane.2d": (MS2 + "_s.add_collider('plane', point={point}, normal={normal}, "
                                         "friction={friction}); _s.step({dt}, 'symplectic'); _s.x",
                                         {"point": ("vector", "[0.0, 0.0]"), "normal": ("vector", "[0.0, 1.0]"),
                                          "friction": ("real", "0.2"), "dt": ("real", "1e-3")}),
    "contact.attach": (FEM3 + "km.contact.attach(_b, dhat={dhat}, friction={friction}, friction_velocity={friction_velocity}, "
                       "tol={tol}, max_newton={max_newton}, barrier_stiffness={barrier_stiffness}); _b.add_collider('plane'); "
                       "_b.step(1e-2); _b.x",
                       {"dhat": ("real", "None"), "friction": ("real", "0.2"), "friction_velocity": ("real", "1e-3"),
                        "tol": ("real", "1e-2"), "max_newton": ("count", "500"), "barrier_stiffness": ("real", "None")}),
    "contact.attach.massspring": (MS3 + "km.contact.attach(_s, triangles={triangles}); "
                                  "_s.add_collider('sphere', center=[0.5, 0.0, 0.5], radius=0.3); _s.step(1e-2); _s.x",
                                  {"triangles": ("index", "CL.triangles")}),
    "fem.Scene.add_body": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + FEM3 + "_c.add_body({body}); "
                           "_c.add_collider('plane'); _c.step(1e-2); _b.x",
                           {"body": ("name", "_b")}),
    "fem.Scene.add_body.massspring": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + MS3 +
                                      "_c.add_body(_s, triangles={triangles}); "
                                      "_c.add_collider('sphere', center=[0.5, 0.0, 0.5], radius=0.3); _c.step(1e-2); _s.x",
                                      {"triangles": ("index", "CL.triangles")}),
    "diff.grid.rollout": (GRID + "_r = km.diff.rollout(_g, {steps}, {dt}, wrt={wrt}, checkpoints={checkpoints}); "
                          "_r.backward({{'u': np.ones_like(_g.u)}})",
                          {"steps": ("count", "2"), "dt": ("real", "0.02"), "wrt": ("name", "('u', 'v', 'viscosity')"),
                           "checkpoints": ("count", "None")}),
    "diff.grid.controls": (GRID + "_r = km.diff.rollout(_g, 2, 0.02, wrt=('controls',), controls={controls}); "
                           "_r.backward({{'v': np.ones_like(_g.v)}})",
                           {"controls": ("array", "np.zeros((2, 8, 8, 2))")}),
    "diff.grid.backward": (SMOKE + "_r = km.diff.rollout(_g, 2, 0.02, wrt=('density', 'u')); "
                           "_r.backward({{'density': {g}}})",
                           {"g": ("array", "np.ones((8, 8))")}),
    "diff.sph.rollout": (WSPH + "_r = km.diff.rollout(_f, {steps}, {dt}, wrt={wrt}, checkpoints={checkpoints}); "
                         "_r.backward({{'x': np.ones_like(_f.x)}})",
                         {"steps": ("count", "2"), "dt": ("real", "1e-4"), "wrt": ("name", "('x', 'v', 'viscosity')"),
                          "checkpoints": ("count", "None")}),
    "diff.sph.controls": (WSPH + "_r = km.diff.rollout(_f, 2, 1e-4, wrt=('controls',), controls={controls}); "
                          "_r.backward({{'v': np.ones_like(_f.v)}})",
                          {"controls": ("array", "np.zeros((2, len(SPH_X), 2))")}),
    "diff.sph.backward": (WSPH + "_r = km.diff.rollout(_f, 2, 1e-4, wrt=('x', 'viscosity')); "
                          "_r.backward({{'v': {g}}})",
                          {"g": ("array", "np.ones_like(SPH_X)")}),
}

BODY_SCENARIOS = {
    # colliders: missing, unknown and contradictory options; bodies a collider cannot hold
    "fem.add_collider.box.no_upper": FEM3 + "_b.add_collider('box', lower=[0, 0, 0]); _b.step(1e-2)",
    "fem.add_collider.sphere.no_radius": FEM3 + "_b.add_collider('sphere', center=[0, -1, 0]); _b.step(1e-2)",
    "fem.add_collider.mesh.no_triangles": FEM3 + "_b.add_collider('mesh', vertices=np.zeros((3, 3))); _b.step(1e-2)",
    "fem.add_collider.mesh.path_missing": FEM3 + "_b.add_collider('mesh', path=TMP + '/none.obj'); _b.step(1e-2)",
    "fem.add_collider.mesh.path_garbage": (FEM3 + "WRITE(TMP + '/g.obj', bytes(range(256))); "
                                           "_b.add_collider('mesh', path=TMP + '/g.obj'); _b.step(1e-2)"),
    "fem.add_collider.mesh.path_none": FEM3 + "_b.add_collider('mesh', path=None); _b.step(1e-2)",
    "fem.add_collider.unknown_option": FEM3 + "_b.add_collider('plane', nromal=[0, 1, 0]); _b.step(1e-2)",
    "fem.add_collider.box.inverted": FEM3 + "_b.add_collider('box', lower=[1, 1, 1], upper=[0, 0, 0]); _b.step(1e-2)",
    "fem.add_collider.box.flat": FEM3 + "_b.add_collider('box', lower=[0, 0, 0], upper=[1, 0, 1]); _b.step(1e-2)",
    "fem.add_collider.plane.zero_normal": FEM3 + "_b.add_collider('plane', normal=[0, 0, 0]); _b.step(1e-2)",
    "fem.add_collider.plane.moving": FEM3 + "_b.add_collider('plane', velocity=[0, 1, 0]); _b.step(1e-2)",
    "fem.add_collider.motion.not_callable": FEM3 + "_b.add_collider('box', lower=[-1, -1, -1], upper=[1, 0, 1], motion=3)",
    "fem.add_collider.motion.nan": (FEM3 + "_b.add_collider('box', lower=[-1, -1, -1], upper=[1, 0, 1], "
                                    "motion=lambda t: [np.nan, 0, 0]); _b.step(1e-2); _b.x"),
    # an exception of the user's own motion function reaches the user unchanged
    "fem.add_collider.motion.raises": (FEM3 + "_ok = False\ntry:\n    _b.add_collider('box', lower=[-1, -1, -1], "
                                       "upper=[1, 0, 1], motion=lambda t: 1 / 0)\nexcept ZeroDivisionError:\n"
                                       "    _ok = True\nassert _ok; _b.x"),
    "fem.add_collider.motion.bad_shape": (FEM3 + "_b.add_collider('box', lower=[-1, -1, -1], upper=[1, 0, 1], "
                                          "motion=lambda t: [1.0, 2.0]); _b.step(1e-2); _b.x"),
    "fem.add_collider.inside": FEM3 + "_b.add_collider('sphere', center=[0.05, 0.1, 0.05], radius=1.0); _b.step(1e-2)",
    "fem.add_collider.huge_radius": FEM3 + "_b.add_collider('sphere', center=[0, -1e300, 0], radius=1e300); _b.step(1e-2)",
    "fem.add_collider.2d.implicit": FEM2 + "_b.add_collider('plane'); _b.step(1e-2)",
    "fem.add_collider.2d.mesh": FEM2 + "_b.add_collider('mesh', vertices=np.zeros((3, 2)), triangles=[[0, 1, 2]])",
    "fem.add_collider.2d.motion": FEM2 + "_b.add_collider('box', lower=[-1, -1], upper=[1, 0], motion=lambda t: [0, 0])",
    "fem.add_collider.2d.inside": FEM2 + "_b.add_collider('sphere', center=[0.05, 0.1], radius=1.0); _b.step(1e-5, 'symplectic'); _b.x",
    "fem.add_collider.2d.tunnel": (FEM2 + "_b.add_collider('sphere', center=[0.05, -1.0], radius=1e-3); "
                                   "_b.v[:] = [0.0, -100.0]; _b.step(1e-3, 'symplectic'); _b.x"),
    "fem.add_collider.symplectic.mesh": (FEM3 + "_b.add_collider('mesh', vertices=[[0.0, 0, 0], [1, 0, 0], [0, 0, 1]], "
                                         "triangles=[[0, 1, 2]]); _b.step(1e-5, 'symplectic')"),
    "fem.add_collider.symplectic.motion": (FEM3 + "_b.add_collider('box', lower=[-1, -1, -1], upper=[1, 0, 1], "
                                           "angular_velocity=[0, 1, 0]); _b.step(1e-5, 'symplectic')"),
    "fem.add_collider.nan_view.x": FEM3 + "_b.add_collider('plane'); _b.x[0, 0] = np.nan; _b.step(1e-2); _b.x",
    "fem.add_collider.nan_view.v.symplectic": (FEM3 + "_b.add_collider('plane'); _b.v[0, 0] = np.nan; "
                                               "_b.step(1e-5, 'symplectic'); _b.x"),
    "fem.add_collider.huge_velocity": FEM3 + "_b.add_collider('plane'); _b.v[:] = 1e300; _b.step(1e-2); _b.x",
    "fem.add_collider.steps_bad": FEM3 + "_b.add_collider('plane'); _b.step(1e-2, steps=0)",
    "fem.add_collider.beta": FEM3 + "_b.add_collider('plane'); _b.step(1e-2, integrator='explicit')",
    "fem.add_collider.integrator_bad": FEM3 + "_b.add_collider('plane'); _b.step(1e-2, integrator='nope')",
    "fem.add_collider.diff": FEM3 + "_b.add_collider('plane'); km.diff.rollout(_b, 2, 1e-2, wrt=('x',))",
    "fem.add_collider.set_state": (FEM3 + "_b.add_collider('plane'); _st = _b.state(); _b.step(1e-2); "
                                   "_b.set_state(_st); _b.step(1e-2); _b.x"),
    "massspring.add_collider.beta": MS3 + "_s.add_collider('plane'); _s.step(1e-2, beta=0.5)",
    "massspring.add_collider.2d.implicit": MS2 + "_s.add_collider('plane'); _s.step(1e-2)",
    "massspring.add_collider.sphere.no_radius": MS2 + "_s.add_collider('sphere', center=[0, 0]); _s.step(1e-3, 'symplectic')",
    "massspring.add_collider.box.no_lower": MS2 + "_s.add_collider('box', upper=[1, 0]); _s.step(1e-3, 'symplectic')",
    "massspring.add_collider.box.3_coords": MS2 + "_s.add_collider('box', lower=[0, 0, 0], upper=[1, 1, 1]); _s.step(1e-3, 'symplectic')",
    "massspring.add_collider.unknown_2d": MS2 + "_s.add_collider('plane', subdivisions=3)",
    "massspring.add_collider.diff": MS3 + "_s.add_collider('plane'); km.diff.rollout(_s, 2, 1e-2, wrt=('x',))",
    "massspring.add_collider.nan_view.symplectic": (MS2 + "_s.add_collider('plane'); _s.x[0, 0] = np.nan; "
                                                    "_s.step(1e-3, 'symplectic'); _s.x"),
    "massspring.add_collider.fixed_all": ("_s = km.massspring.System(CL.x, CL.springs, stiffness=100.0, "
                                          "fixed=np.arange(len(CL.x)), gravity=[0, -9.81, 0]); "
                                          "_s.add_collider('plane'); _s.step(1e-2); _s.x"),
    "massspring.add_collider.no_springs": ("_s = km.massspring.System(CL.x, np.zeros((0, 2), int), stiffness=1.0, "
                                           "gravity=[0, -9.81, 0]); _s.add_collider('plane'); _s.step(1e-2); _s.x"),
    "massspring.add_collider.one_vertex": ("_s = km.massspring.System([[0.0, 1.0, 0.0]], np.zeros((0, 2), int), "
                                           "stiffness=1.0, gravity=[0, -9.81, 0]); _s.add_collider('plane'); "
                                           "_s.step(1e-2); _s.x"),
    "contact.attach.twice_different": FEM3 + "km.contact.attach(_b, dhat=1e-3); km.contact.attach(_b, dhat=2e-3)",
    "contact.attach.not_a_body": "km.contact.attach(object())",
    "contact.attach.sph": "km.contact.attach(km.sph.Fluid(SPH_X, 0.02))",
    "contact.attach.fem_triangles": FEM3 + "km.contact.attach(_b, triangles=[[0, 1, 2]]); _b.add_collider('plane'); _b.step(1e-2)",
    "contact.attach.triangles_nan": MS3 + "km.contact.attach(_s, triangles=CL.triangles * np.nan); _s.add_collider('plane'); _s.step(1e-2)",
    "contact.attach.friction_bad_late": FEM3 + "km.contact.attach(_b, friction=-1.0); _b.add_collider('plane')",
    "fem.Scene.add_body.2d": "_c = km.fem.Scene(); " + FEM2 + "_c.add_body(_b)",
    "fem.Scene.add_body.gravity": "_c = km.fem.Scene(); " + FEM3 + "_c.add_body(_b)",
    "fem.Scene.add_body.twice": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + FEM3 + "_c.add_body(_b); _c.add_body(_b); "
                                 "_c.step(1e-2); _b.x"),
    "fem.Scene.add_body.fem_triangles": "_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + FEM3 + "_c.add_body(_b, triangles=[[0, 1, 2]])",
    "fem.Scene.add_body.nan_view": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + FEM3 + "_b.x[0, 0] = np.nan; "
                                    "_c.add_body(_b); _c.step(1e-2); _b.x"),
    "fem.Scene.add_body.nan_later": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + FEM3 + "_c.add_body(_b); "
                                     "_b.x[0, 0] = np.nan; _c.step(1e-2); _b.x"),
    "fem.Scene.add_body.not_a_body": "km.fem.Scene().add_body(km.sph.Fluid(SPH_X, 0.02))",
    "fem.Scene.add_body.triangles_out_of_range": ("_c = km.fem.Scene(gravity=[0, -9.81, 0]); " + MS3 +
                                                  "_c.add_body(_s, triangles=[[0, 1, 10**6]])"),
    # km.diff over km.grid and km.sph
    "diff.grid.no_slip": "_g = km.grid.Fluid((8, 8), 0.1, walls='no_slip'); km.diff.rollout(_g, 2, 0.01, wrt=('u',))",
    "diff.grid.confinement": "_g = km.grid.Fluid((8, 8), 0.1, vorticity_confinement=0.3); km.diff.rollout(_g, 2, 0.01, wrt=('u',))",
    "diff.grid.option": GRID + "km.diff.rollout(_g, 2, 0.01, wrt=('u',), cfl=0.5)",
    "diff.grid.wrt_pressure": GRID + "km.diff.rollout(_g, 2, 0.01, wrt=('pressure',))",
    "diff.grid.wrt_density_no_smoke": GRID + "km.diff.rollout(_g, 2, 0.01, wrt=('density',))",
    "diff.grid.controls_without_wrt": GRID + "_r = km.diff.rollout(_g, 2, 0.02, wrt=('u',), controls=np.ones((2, 8, 8, 2))); _r.backward({'u': np.ones((9, 8))})",
    "diff.grid.controls_missing": GRID + "km.diff.rollout(_g, 2, 0.02, wrt=('controls',))",
    "diff.grid.controls_3d_shape": GRID + "km.diff.rollout(_g, 2, 0.02, wrt=('controls',), controls=np.ones((2, 8, 8, 3)))",
    "diff.grid.controls_huge": GRID + "_r = km.diff.rollout(_g, 2, 0.02, wrt=('controls',), controls=np.full((2, 8, 8, 2), 1e300)); _r.backward({'u': np.ones((9, 8))})",
    "diff.grid.nan_view": GRID + "_g.u[3, 3] = np.nan; _r = km.diff.rollout(_g, 2, 0.02, wrt=('u',)); _r.backward({'u': np.ones((9, 8))})",
    "diff.grid.viscosity_negative": GRID + "_g._diff_set('viscosity', -1.0)",
    "diff.grid.backward_unknown": GRID + "km.diff.rollout(_g, 2, 0.02, wrt=('u',)).backward({'w': np.ones((8, 8))})",
    "diff.grid.backward_nan": GRID + "km.diff.rollout(_g, 2, 0.02, wrt=('u',)).backward({'u': np.full((9, 8), np.nan)})",
    "diff.grid.backward_shape": GRID + "km.diff.rollout(_g, 2, 0.02, wrt=('u',)).backward({'u': np.ones((8, 9))})",
    "diff.grid.torch": (GRID + TORCH + "_u = _t.zeros((9, 8), dtype=_t.float64, requires_grad=True); "
                        "_o = km.torch.rollout(_g, 2, 0.02, {'u': _u}); _o['u'].sum().backward(); _u.grad.numpy()"),
    "diff.grid.torch.bad_name": GRID + TORCH + "km.torch.rollout(_g, 2, 0.02, {'pressure': _t.zeros((8, 8))})",
    "diff.grid.torch.shape": GRID + TORCH + "km.torch.rollout(_g, 2, 0.02, {'u': _t.zeros((8, 8), dtype=_t.float64)})",
    "diff.grid.3d": ("_g = km.grid.Fluid((4, 4, 4), 0.25, tol=1e-8); "
                     "_r = km.diff.rollout(_g, 2, 0.02, wrt=('w', 'controls'), controls=np.ones((2, 4, 4, 4, 2))); _r"),
    "diff.sph.dfsph": "_f = km.sph.Fluid(SPH_X, 0.02); km.diff.rollout(_f, 2, 1e-4, wrt=('x',))",
    "diff.sph.dfsph.torch": "_f = km.sph.Fluid(SPH_X, 0.02); " + TORCH + "km.torch.rollout(_f, 2, 1e-4, {'x': _t.tensor(_f.x)})",
    "diff.sph.option": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('x',), cfl=0.4)",
    "diff.sph.wrt_rho0": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('rho0',))",
    "diff.sph.wrt_str": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt='xv')",
    "diff.sph.controls_missing": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('controls',))",
    "diff.sph.controls_transposed": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('controls',), controls=np.zeros((2, 2, len(SPH_X))))",
    "diff.sph.controls_one_step": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('controls',), controls=np.zeros((len(SPH_X), 2)))",
    "diff.sph.controls_huge": (WSPH + "_r = km.diff.rollout(_f, 2, 1e-4, wrt=('controls',), "
                               "controls=np.full((2, len(SPH_X), 2), 1e300)); _r.backward({'x': np.ones_like(_f.x)})"),
    "diff.sph.nan_view": WSPH + "_f.v[0, 0] = np.nan; km.diff.rollout(_f, 2, 1e-4, wrt=('x',)).backward({'x': np.ones_like(_f.x)})",
    "diff.sph.dt_huge": WSPH + "km.diff.rollout(_f, 2, 1.0, wrt=('x',)).backward({'x': np.ones_like(_f.x)})",
    "diff.sph.backward_unknown": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('x',)).backward({'rho': np.ones(len(SPH_X))})",
    "diff.sph.backward_inf": WSPH + "km.diff.rollout(_f, 2, 1e-4, wrt=('x',)).backward({'x': np.full(SPH_X.shape, np.inf)})",
    "diff.sph.viscosity_nan": WSPH + "_f._diff_set('viscosity', float('nan'))",
    "diff.sph.torch.viscosity": (WSPH + TORCH + "_nu = _t.tensor(1e-3, dtype=_t.float64, requires_grad=True); "
                                 "_o = km.torch.rollout(_f, 2, 1e-4, {'viscosity': _nu}); _o['x'].sum().backward(); "
                                 "float(_nu.grad)"),
    "diff.sph.3d": ("_f = km.sph.Fluid(km.sph.block([0, 0, 0], [0.06, 0.06, 0.06], 0.02) + 0.01, 0.02, method='wcsph', "
                    "domain=([0, 0, 0], [0.1, 0.1, 0.1])); _r = km.diff.rollout(_f, 2, 1e-4, wrt=('x', 'controls'), "
                    "controls=np.zeros((2, _f.n, 3))); _r.backward({'x': np.ones_like(_f.x)})"),
}
BODY_FAST = {"fem.add_collider.box.no_upper", "fem.add_collider.sphere.no_radius", "fem.add_collider.2d.implicit",
             "fem.add_collider.2d.tunnel", "fem.add_collider.motion.nan", "massspring.add_collider.box.no_lower",
             "contact.attach.twice_different", "fem.Scene.add_body.twice", "diff.grid.controls_3d_shape",
             "diff.grid.nan_view", "diff.sph.dfsph", "diff.sph.controls_transposed", "diff.sph.nan_view"}


def _body_cases():
    out = []
    for case in _entry_cases(BODY_ENTRIES, 0, 3.0):  # the base calls in the fast subset, the bad values not
        out.append(dict(case, setup=SETUP_BODIES))
    for sid, expr in BODY_SCENARIOS.items():
        out.append(dict(id=sid, setup=SETUP_BODIES, expr=expr, arg=None, interrupt=3.0, fast=sid in BODY_FAST))
    return out


_cases_before_bodies = cases


def cases():  # noqa: F811 - the list above, then the review round's cases
    return _cases_before_bodies() + _body_cases()
