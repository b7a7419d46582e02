// Embedded tetrahedral mesh with crack surfaces (peridynamics paper, Sec. 5.2): one particle per
// tetrahedron (at its barycentre); the mesh follows the particles and is split along the faces
// between tetrahedra whose bond broke, so each frame's surface shows the original boundary and
// the crack faces.
//
// Topology: every interior face joins two tetrahedra, whose particles share a bond (when their
// barycentres are within the horizon; a face without a bond never cracks). When that bond breaks
// the face joins the crack face set and its three vertices are examined: a vertex whose incident
// tetrahedra fall into several groups connected through uncracked faces is split, one copy per
// group (the group with the lowest tetrahedron keeps the vertex), as the paper does. Motion
// (eqs. 19-21): each vertex moves with the mass-weighted mean velocity of the particles of its
// incident tetrahedra, each weighing 1/4 m_p.
//
// Storage is fixed-size (vertices up to 4 per tetrahedron, the fully shattered limit), so a
// checkpoint is a plain copy of the arrays and a resumed run continues bitwise.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/math/types.hpp"
#include "kernels/peridynamics.hpp"

namespace amalgam {

class PdCrackMesh {
 public:
  // tets: 4 node indices each (into nodes); tetrahedron t is particle first_particle + t.
  PdCrackMesh(const std::vector<Vec3d>& nodes, const std::vector<std::array<std::int32_t, 4>>& tets,
              std::uint32_t first_particle);

  // Finds each face's bond (after the solver built its bonds), and marks faces whose bond is
  // already broken (pre-cracks) as cracked.
  void attach(const PdBonds& bonds);
  // After the bond arrays changed layout (compaction, or a checkpoint's rows restored): finds the
  // bond of every face that is not cracked again (it must still be stored: compaction keeps intact
  // bonds, and a broken one cracked its face in the step it broke).
  void reattach(const PdBonds& bonds);
  // Adds the faces whose bond broke since the last call to the crack set and splits vertices.
  // Returns the number of vertices created.
  std::size_t update_topology(const PdBonds& bonds);
  // x_v += dt v_v, v_v the 1/4 m_p-weighted mean of the incident particles' velocities (eqs.
  // 19-21); mass = density x volume per particle.
  void move_vertices(const Vec3* v, const Real* volume, const std::int32_t* material,
                     const PdMaterial* materials, Real dt);
  // The velocity move_vertices gives each vertex (eqs. 19, 20), from the particles' velocities:
  // `weight` and `velocity` get one entry per vertex in use (0 for a vertex without particles).
  void vertex_velocities(const Vec3* v, const Real* volume, const std::int32_t* material,
                         const PdMaterial* materials, std::vector<double>& weight,
                         std::vector<Vec3d>& velocity) const;

  // The surface: original boundary faces and both sides of every crack face, outward-oriented
  // triangles over the used vertices only (compact indices); crack[f] = 1 for crack faces. With
  // `vertex_velocity` (vertex_velocities()), `velocity` gets the velocity of each vertex written.
  void surface(std::vector<Vec3>& vertices, std::vector<std::array<std::uint32_t, 3>>& triangles,
               std::vector<std::uint8_t>& crack,
               const std::vector<Vec3d>* vertex_velocity = nullptr,
               std::vector<Vec3>* velocity = nullptr) const;

  std::size_t tetrahedra() const { return tets_.size(); }
  std::size_t vertices() const { return std::size_t(vertex_count_); }
  std::size_t crack_faces() const;
  const std::vector<std::array<std::uint32_t, 4>>& tets() const { return tets_; }
  const std::vector<Vec3>& positions() const { return x_; }  // first vertices() are in use

  // State for checkpoints: (name, pointer, bytes) of every array that changes during a run.
  struct StateArray {
    std::string name;
    char* data;
    std::size_t bytes;
  };
  std::vector<StateArray> state();
  // After the state arrays were read back: rebuilds what derives from them.
  void restored() { rebuild_incidence(); }

 private:
  struct Face {
    std::uint32_t tet[2];        // tet[1] = none on the boundary
    std::uint8_t local[2];       // the face is opposite local vertex `local[s]` of tet[s]
    std::uint64_t bond = kNone;  // bond tet[0] -> tet[1] (row of tet[0]'s particle)
  };
  static constexpr std::uint64_t kNone = ~std::uint64_t(0);
  void split_vertex(std::uint32_t v);
  std::uint64_t find_bond(const PdBonds& bonds,
                          const Face& f) const;  // kNone: no bond joins the pair

  std::uint32_t first_particle_;
  std::vector<std::array<std::uint32_t, 4>> tets_;       // current vertex indices (split copies)
  std::vector<std::array<std::uint32_t, 4>> tet_faces_;  // face index opposite each local vertex
  std::vector<std::array<std::uint8_t, 12>> outward_;    // per face: local vertex order, outward
  std::vector<Face> faces_;
  std::vector<std::uint8_t> cracked_;  // per face
  std::vector<Vec3> x_;                // capacity 4 x tetrahedra
  std::uint64_t vertex_count_ = 0;
  std::vector<std::vector<std::uint32_t>>
      incident_;                // per vertex: its tetrahedra (rebuilt on resume)
  std::vector<double> weight_;  // scratch for move_vertices
  std::vector<Vec3d> velocity_;
  void rebuild_incidence();
};

}  // namespace amalgam
