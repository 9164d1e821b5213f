// Config, Model and State of the contact solver (solver.h): several deformable bodies
// (tetrahedral solids, triangle cloths with springs), static triangle-mesh obstacles and
// half-space colliders, all sharing one vertex array so that body-body, self and obstacle
// contact are one collision mesh (Li et al., "Incremental Potential Contact", 2020).
#pragma once

#include <string>
#include <vector>

#include "contact/distance.h"
#include "core/types.h"
#include "fem/kernels.h"
#include "linalg/spd_solver.h"

namespace kinema::contact {

// How a barrier term's Hessian is made positive semidefinite: not at all (None), by clamping
// its negative eigenvalues to zero (Clamp: the nearest PSD matrix, Li et al. 2020 sec. 4.2, as
// the IPC toolkit's CLAMP), or by the rank-one Gauss-Newton matrix of barrier.h (RankOne: the
// clamped first term b'' grad d grad d^T + b' grad d grad d^T / (2 d), no eigenproblem; Clamp
// where the edge mollifier is active).
enum class Projection { None, Clamp, RankOne };

struct Config {
  Vec3 gravity = Vec3::Zero();       // [m/s^2]
  Scalar dhat = 1e-3;                // barrier activation distance [m]
  Scalar barrier_stiffness = 0;      // kappa [J/m^4]; 0: chosen from the masses (Li et al. 2020, sec. 4.3)
  Scalar friction = 0;               // Coulomb coefficient mu
  Scalar friction_velocity = 1e-3;   // eps_v: slip speed below which friction is smoothed [m/s]
  Scalar tol = 1e-2;                 // Newton stops when max |dx| / dt < tol * bbox diagonal [1/s]
  Index max_newton = 500;
  LinearSolver linear_solver = LinearSolver::CholmodDirect;
  // With CholmodDirect: factorise by the 3x3-block Cholesky (contact/block_cholesky.h; AMD
  // order, analysed once per pattern) instead of CHOLMOD's supernodal factorisation, which
  // loses on the small, thin systems of a contact scene (a few hundred vertices: its
  // supernodes are tiny BLAS calls).
  bool simplicial = true;
  // Keep the Newton matrix's pattern (elastic blocks plus the contact blocks seen so far) and
  // its symbolic analysis between iterations and steps; false: a pattern of exactly this
  // iteration's blocks, analysed afresh whenever it changes (the former behaviour; for tests
  // and benchmarks).
  bool reuse_pattern = true;
  // The barrier Hessians in the Newton matrix: the rank-one Gauss-Newton matrices (barrier.h),
  // or the eigen clamp of each (the former behaviour).
  Projection barrier_projection = Projection::RankOne;
};

struct Plane {
  Vec3 point, normal;  // normal: unit, pointing into the allowed side
  Scalar friction = -1;  // Coulomb mu of contacts with this plane; < 0: Config::friction
  // >= 0: a moving (scripted) plane, translated with this driven vertex of the model, which is
  // its point (`point` is then unused): the plane's offset is an unknown of the solve held to
  // its script like a moving obstacle's vertices, so CCD and the barrier see it move.
  Index vertex = -1;

  Vec3 point_at(const Scalar* x) const {
    return vertex >= 0 ? Vec3(Eigen::Map<const Vec3>(x + 3 * vertex)) : point;
  }
};

struct Model {
  // Vertices of every body and obstacle, in the order they were added.
  Index vertex_count = 0;
  std::vector<Scalar> rest;   // (n, 3) initial positions [m]
  std::vector<Scalar> mass;   // (n,) lumped masses [kg]; 0 for obstacle vertices
  std::vector<char> fixed;    // (n,) not a degree of freedom (obstacles, pinned vertices)
  std::vector<Index> body;    // (n,) body id of each vertex
  std::vector<Scalar> damping;  // (n,) mass-proportional damping c [1/s] (force -c m v)
  // (n,) obstacle vertices moved by a script: degrees of freedom held to State::target by an
  // augmented-Lagrangian spring, so the collider's motion is inside the CCD-clamped solve.
  std::vector<char> driven;

  // Tetrahedral elasticity: Sifakis & Barbic 2012 (fem/kernels.h).
  std::vector<Index> tets;                     // (T, 4)
  std::vector<fem::Mat<3>> tet_dm_inv;
  std::vector<Scalar> tet_volume, tet_mu, tet_lambda;
  std::vector<fem::Material> tet_material;

  // Springs (cloth stretch, shear and bending): massspring/kernels.h.
  std::vector<Index> springs;                  // (S, 2)
  std::vector<Scalar> spring_stiffness, spring_rest;
  std::vector<Scalar> spring_damping;          // c [N s/m] along the spring (direction lagged at x_n)

  // Collision mesh: triangles (tet boundaries, cloths, obstacles), their unique edges and the
  // vertices they use.
  std::vector<Index> faces, edges, points;
  std::vector<Plane> planes;

  Index body_count = 0;
  // (body_count,) Coulomb mu of contacts with each body (colliders given their own); < 0:
  // Config::friction. A contact takes the coefficient of the first vertex of its stencil whose
  // body has one (a collider, since pairs join a body to a collider or to another body).
  std::vector<Scalar> body_friction;

  // Each adder returns the index of its first vertex; inputs are validated with messages
  // naming the argument.
  // youngs_modulus, poisson_ratio: one value (param_count 1) or one per tet (param_count m);
  // damping: mass-proportional c [1/s].
  Index add_solid(const Scalar* x, Index n, const Index* tets, Index m, fem::Material material,
                  const Scalar* youngs_modulus, const Scalar* poisson_ratio, Index param_count, Scalar density,
                  Scalar damping, const Index* fixed_ids, Index fixed_count);
  Index add_cloth(const Scalar* x, Index n, const Index* triangles, Index m, const Index* springs,
                  Index spring_count, Scalar stiffness, Scalar density, const Index* fixed_ids,
                  Index fixed_count);
  // A mass-spring body (km.massspring): per-spring stiffness [N/m], rest length [m] and
  // damping [N s/m], per-vertex mass [kg]; its collision surface is `triangles` (m may be 0:
  // then its vertices collide as points only).
  Index add_springs(const Scalar* x, Index n, const Index* spring_ids, Index spring_count, const Scalar* stiffness,
                    const Scalar* rest_length, const Scalar* spring_damping, const Scalar* masses,
                    const Index* triangles, Index m, const Index* fixed_ids, Index fixed_count);
  // friction: the collider's own Coulomb mu (>= 0), or < 0 for the scene's.
  Index add_obstacle(const Scalar* x, Index n, const Index* triangles, Index m, bool moving = false,
                     Scalar friction = -1);
  // moving: the plane translates with a driven vertex at `point` (returned; -1 when static).
  Index add_plane(const Vec3& point, const Vec3& normal, Scalar friction = -1, bool moving = false);

  Scalar total_mass() const;
  Scalar bbox_diagonal(const Scalar* x) const;

 private:
  Index append_vertices(const Scalar* x, Index n, const char* name);
  void add_surface(const std::vector<Index>& triangles);
};

// What evolves: positions, velocities, time, and the barrier stiffness (raised during a step
// when contacts get too close, Li et al. 2020 sec. 4.3, so a copy resumes exactly).
struct State {
  std::vector<Scalar> x, v;  // (n, 3) [m], [m/s]
  Scalar time = 0;           // [s]
  Scalar kappa = 0;          // barrier stiffness in use [J/m^4]; 0 until the first step
  // (n, 3) positions the driven (scripted) obstacle vertices reach at the end of the next step
  // [m]; an input set before each step, ignored for every other vertex.
  std::vector<Scalar> target;
};

State make_state(const Model& model);

}  // namespace kinema::contact
