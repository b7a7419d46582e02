// Builds the Simulation of a parsed scene (solvers/scene_spec.hpp): samples the objects, bakes
// mesh colliders, adds the particles and the method's sets (particle domains, boundary
// conditions, pre-cracks, crack meshes), and initialises. Set-up work (sampling, voxelisation,
// bond families) runs on `space`, OpenVDB's tools under its thread limit. Throws InputError for
// what only set-up finds (a collider whose distance field would be too large).
#pragma once

#include <memory>
#include <vector>

#include "core/exec/exec.hpp"
#include "solvers/mpm_solver.hpp"
#include "solvers/pd_solver.hpp"
#include "solvers/scene_spec.hpp"
#include "solvers/simulation.hpp"

namespace amalgam {

// The scene's colliders; mesh and .vdb colliders with their sparse fields (built lazily later).
std::vector<Collider> build_colliders(const SceneSpec& scene,
                                      const exec::Space& space = exec::Space());
// The MPM solver of an MPM scene with its particles (and particle domains).
MpmSolver build_solver(const SceneSpec& scene, const exec::Space& space = exec::Space());
// The peridynamic solver of a peridynamics scene with its particles and boundary sets, not yet
// initialised.
PdSolver build_pd_solver(const SceneSpec& scene, const exec::Space& space = exec::Space());
// The scene's Simulation, ready to step.
std::unique_ptr<Simulation> make_simulation(const SceneSpec& scene, const exec::Space& space);

}  // namespace amalgam
