#include "solvers/object_contact.hpp"

#include <algorithm>
#include <sstream>
#include <stdexcept>

#include "core/errors.hpp"
#include "solvers/configuration_maps.hpp"

namespace amalgam {

ObjectContact::ObjectContact() {
  x_ = points_.add("x", AttrType::Real, 3);
  v_ = points_.add("v", AttrType::Real, 3);
  m_ = points_.add("m", AttrType::Real, 1);
  object_ = points_.add("object", AttrType::Int32, 1);
  leaf_ = points_.add("leaf", AttrType::Int32, 1);
  offset_ = points_.add("offset", AttrType::Int32, 1);
  grid_.set_node4_channels(2);  // (M, P), (K, var)
}

void ObjectContact::map_leaves(const exec::Space& space, const SparseGrid& ref,
                               const BinTable& bins, const std::int32_t* particle_object) {
  leaf_object_.assign(ref.leaf_count(), -1);
  objects_ = 0;
  ordered_leaves_ = ref.active_leaves();
  const auto& lc = ref.leaf_coords();
  std::sort(ordered_leaves_.begin(), ordered_leaves_.end(), [&lc](std::int32_t a, std::int32_t b) {
    const Vec3i &p = lc[size_t(a)], &q = lc[size_t(b)];
    return p[0] != q[0] ? p[0] < q[0] : p[1] != q[1] ? p[1] < q[1] : p[2] < q[2];
  });
  std::int32_t* lo = leaf_object_.data();
  const auto& nbr8 = ref.nbr8();
  const auto& cstart = ref.colour_start();
  const auto& cbins = ref.colour_bins();
  struct Conflict {
    std::int64_t bin = -1;
    int a = 0, b = 0;
    int objects = 0;  // 1 + the largest object index seen
  };
  // Same-colour bins reach disjoint leaves: each colour's bins write their leaves in parallel.
  for (int c = 0; c < 8; ++c) {
    const std::uint32_t c0 = cstart[size_t(c)], c1 = cstart[size_t(c) + 1];
    const Conflict bad = exec::parallel_reduce(
        space, "contact.map_leaves", exec::Index(c1 - c0), Conflict{},
        [&](exec::Index ci, Conflict& acc) {
          const std::uint32_t b = cbins[c0 + std::uint32_t(ci)];
          const std::int32_t k = particle_object[bins.start[b]];
          for (std::uint32_t p = bins.start[b] + 1; p < bins.start[b + 1]; ++p)
            if (particle_object[p] != k && acc.bin < 0)
              acc.bin = std::int64_t(b), acc.a = k, acc.b = particle_object[p];
          for (const std::int32_t leaf : nbr8[b]) {
            std::int32_t& owner = lo[leaf];
            if (owner >= 0 && owner != k && acc.bin < 0)
              acc.bin = std::int64_t(b), acc.a = owner, acc.b = k;
            owner = k;
          }
          acc.objects = std::max(acc.objects, k + 1);
        },
        [](Conflict x, const Conflict& y) {
          const int objects = std::max(x.objects, y.objects);
          x = x.bin >= 0 ? x : y;
          x.objects = objects;
          return x;
        });
    objects_ = std::max(objects_, bad.objects);
    if (bad.bin >= 0) {
      std::ostringstream os;
      os << "objects " << std::min(bad.a, bad.b) << " and " << std::max(bad.a, bad.b)
         << " reach the same reference-grid leaf: each object's reference configuration lives in its "
         << "own lane of " << ConfigurationMaps::kLaneCells
         << " cells along x, and an object is now more than that from where its configuration was last "
         << "reset (let it reset: \"update\": \"adaptive\" or \"eulerian\", or start the objects closer "
         << "together)";
      throw SimulationError(os.str());
    }
  }
}

ContactPointView ObjectContact::point_view() {
  return {points_.vec3(x_),     points_.vec3(v_),       points_.real(m_), points_.int32(object_),
          points_.int32(leaf_), points_.int32(offset_), points_.size()};
}

std::size_t ObjectContact::apply(const exec::Space& space, const MpmGridView& ref_view,
                                 const Real* q, const ObjectContactSettings& settings, Real dx,
                                 Real dt) {
  if (settings.mode == ObjectContactMode::None) return 0;
  if (ordered_leaves_.size() != ref_view.nactive)
    throw std::logic_error(
        "ObjectContact::apply: map_leaves was not called after the topology changed");
  MpmGridView ref = ref_view;
  ref.active_leaves = ordered_leaves_.data();
  // 1. broad phase (object boxes) and collection: a deterministic compaction (count per active
  // leaf, prefix sum, fill) of the points near another object.
  const ContactBoxes boxes = contact_boxes(space, ref, q, leaf_object_.data(), objects_, dt);
  const Real margin = 6 * dx;
  count_.resize(ref.nactive);
  start_.resize(ref.nactive);
  contact_count_points(space, ref, q, leaf_object_.data(), boxes, margin, dt, count_.data());
  const std::uint32_t* cnt = count_.data();
  const std::uint32_t total = exec::parallel_scan<std::uint32_t>(
      space, "contact.scan", exec::Index(ref.nactive), [cnt](exec::Index i) { return cnt[i]; },
      start_.data());
  points_.resize(total);
  if (total == 0) return 0;  // objects apart: no global grid this substep
  ContactPointView pts = point_view();
  contact_collect_points(space, ref, q, leaf_object_.data(), boxes, margin, dt, start_.data(), pts);
  // 2. bin the points by global leaf (quadratic stencils) and activate the global grid.
  {
    exec::ScopedRegion region(space.profiler(), "contact.sort");
    binning_.sort_and_bin(space, points_, x_, dx, 2, bins_);
  }
  grid_.update_topology(space, bins_);
  pts = point_view();  // permuted by the sort
  const MpmGridView g = make_grid_view(grid_, bins_, grid_.node4(0), grid_.node4(1));
  ObjectContactParams prm;
  prm.mode = settings.mode;
  prm.friction = settings.friction;
  prm.dx = dx;
  prm.dt = dt;
  // 3. scatter, 4. gather and correct.
  contact_scatter(space, pts, g, prm);
  return contact_gather(space, pts, g, ref, prm);
}

}  // namespace amalgam
