#include "solvers/object_contact.hpp"

#include <algorithm>
#include <cstring>
#include <sstream>
#include <stdexcept>

#include "core/dist/comm.hpp"
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
                               const BinTable& bins, const std::int32_t* particle_object,
                               const ContactRanks* ranks) {
  leaf_object_.assign(ref.leaf_count(), -1);
  objects_ = 0;
  distributed_ = ranks != nullptr;
  mapped_active_ = ref.active_leaves().size();
  ordered_leaves_ = ranks ? *ranks->owned : ref.active_leaves();
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
  Conflict first;
  // Same-colour bins reach disjoint leaves: each colour's bins write their leaves in parallel.
  for (int c = 0; c < 8 && first.bin < 0; ++c) {
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
    if (bad.bin >= 0) first = bad;
  }
  if (ranks) {
    // The objects of the ghost leaves this rank's bins reach go to the leaves' owners (which may
    // have no bin there), who check them against their own; then the first rank's conflict.
    const dist::Comm& comm = dist::Comm::world();
    std::vector<std::uint8_t> owned(ref.leaf_count(), 0);
    for (const std::int32_t li : *ranks->owned) owned[size_t(li)] = 1;
    std::vector<std::vector<std::int32_t>> send(size_t(comm.size()));
    for (const std::int32_t li : ref.active_leaves())
      if (!owned[size_t(li)] && lo[li] >= 0) {
        const Vec3i& l = lc[size_t(li)];
        send[size_t(ranks->owner(l))].insert(send[size_t(ranks->owner(l))].end(),
                                             {l[0], l[1], l[2], lo[li]});
      }
    std::vector<std::vector<char>> bytes;
    for (const auto& v : send) bytes.push_back(dist::as_bytes(v));
    for (const std::vector<char>& in :
         ranks->peers ? comm.alltoall(bytes, *ranks->peers) : comm.alltoall(bytes)) {
      const std::vector<std::int32_t> h = dist::from_bytes<std::int32_t>(in);
      for (size_t i = 0; i + 3 < h.size(); i += 4) {
        const std::int32_t li = ref.find_leaf(Vec3i(h[i], h[i + 1], h[i + 2]) * kLeafDim);
        if (li < 0) continue;
        const int k = h[i + 3];
        if (lo[li] >= 0 && lo[li] != k && first.bin < 0)
          first.bin = 0, first.a = lo[li], first.b = k;
        lo[li] = k;
        objects_ = std::max(objects_, k + 1);
      }
    }
    objects_ = int(comm.max(std::int64_t(objects_)));
    const std::vector<std::int32_t> mine =
        first.bin >= 0 ? std::vector<std::int32_t>{first.a, first.b} : std::vector<std::int32_t>{};
    const std::vector<std::int32_t> all =
        dist::from_bytes<std::int32_t>(comm.allgather(dist::as_bytes(mine), nullptr));
    if (all.size() >= 2) first.bin = 0, first.a = all[0], first.b = all[1];
  }
  {
    const Conflict& bad = first;
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
  if (mapped_active_ != ref_view.nactive)
    throw std::logic_error(
        "ObjectContact::apply: map_leaves was not called after the topology changed");
  MpmGridView ref = ref_view;
  ref.active_leaves = ordered_leaves_.data();
  ref.nactive = ordered_leaves_.size();
  // 1. broad phase (object boxes) and collection: a deterministic compaction (count per active
  // leaf, prefix sum, fill) of the points near another object.
  ContactBoxes boxes = contact_boxes(space, ref, q, leaf_object_.data(), objects_, dt);
  if (distributed_) reduce_boxes(boxes);
  const Real margin = 6 * dx;
  count_.resize(ref.nactive);
  start_.resize(ref.nactive);
  contact_count_points(space, ref, q, leaf_object_.data(), boxes, margin, dt, count_.data());
  const std::uint32_t* cnt = count_.data();
  std::uint32_t total = exec::parallel_scan<std::uint32_t>(
      space, "contact.scan", exec::Index(ref.nactive), [cnt](exec::Index i) { return cnt[i]; },
      start_.data());
  points_.resize(total);
  if (total > 0)
    contact_collect_points(space, ref, q, leaf_object_.data(), boxes, margin, dt, start_.data(),
                           point_view());
  if (distributed_) total = gather_points(ref);
  if (total == 0) return 0;  // objects apart: no global grid this substep
  ContactPointView pts = point_view();
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
  const std::size_t changed = contact_gather(space, pts, g, ref, prm);
  return distributed_ ? std::size_t(dist::Comm::world().sum(std::uint64_t(changed))) : changed;
}

// Every rank's object boxes, combined by exact minima and maxima.
void ObjectContact::reduce_boxes(ContactBoxes& boxes) const {
  const dist::Comm& comm = dist::Comm::world();
  std::vector<Real> mine;
  for (int k = 0; k < boxes.n; ++k)
    for (int a = 0; a < 3; ++a) mine.push_back(boxes.lo[k][a]), mine.push_back(boxes.hi[k][a]);
  const std::vector<Real> all =
      dist::from_bytes<Real>(comm.allgather(dist::as_bytes(mine), nullptr));
  for (std::size_t r = 0; r + mine.size() <= all.size(); r += mine.size())
    for (int k = 0, i = 0; k < boxes.n; ++k)
      for (int a = 0; a < 3; ++a, i += 2) {
        boxes.lo[k][a] = std::min(boxes.lo[k][a], all[r + std::size_t(i)]);
        boxes.hi[k][a] = std::max(boxes.hi[k][a], all[r + std::size_t(i) + 1]);
      }
}

// Every rank's contact points, in the single process's order: by reference leaf coordinate (its
// ordered_leaves_), then node offset. The points of other ranks get leaf -1 (scattered only).
std::uint32_t ObjectContact::gather_points(const MpmGridView& ref) {
  struct Point {
    Real x[3], v[3], m;
    std::int32_t object, offset, leaf, lc[3];
  };
  const dist::Comm& comm = dist::Comm::world();
  const ContactPointView mine_view = point_view();
  std::vector<Point> mine(mine_view.n);
  for (std::size_t p = 0; p < mine.size(); ++p) {
    Point& o = mine[p];
    for (int a = 0; a < 3; ++a) o.x[a] = mine_view.x[p][a], o.v[a] = mine_view.v[p][a];
    o.m = mine_view.m[p];
    o.object = mine_view.object[p];
    o.offset = mine_view.offset[p];
    o.leaf = mine_view.leaf[p];
    const Vec3i& l = ref.leaf_coord[std::size_t(o.leaf)];
    for (int a = 0; a < 3; ++a) o.lc[a] = l[a];
  }
  std::vector<std::size_t> sizes;
  std::vector<Point> all = dist::from_bytes<Point>(comm.allgather(dist::as_bytes(mine), &sizes));
  std::size_t first = 0;  // this rank's points in `all`
  for (int r = 0; r < comm.rank(); ++r) first += sizes[std::size_t(r)] / sizeof(Point);
  for (std::size_t i = 0; i < all.size(); ++i)
    if (i < first || i >= first + mine.size()) all[i].leaf = -1;
  std::vector<std::uint32_t> order(all.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = std::uint32_t(i);
  std::sort(order.begin(), order.end(), [&all](std::uint32_t a, std::uint32_t b) {
    const Point &p = all[a], &q = all[b];
    for (int k = 0; k < 3; ++k)
      if (p.lc[k] != q.lc[k]) return p.lc[k] < q.lc[k];
    return p.offset < q.offset;
  });
  points_.resize(all.size());
  const ContactPointView out = point_view();
  for (std::size_t i = 0; i < all.size(); ++i) {
    const Point& o = all[order[i]];
    out.x[i] = Vec3(o.x[0], o.x[1], o.x[2]);
    out.v[i] = Vec3(o.v[0], o.v[1], o.v[2]);
    out.m[i] = o.m;
    out.object[i] = o.object;
    out.offset[i] = o.offset;
    out.leaf[i] = o.leaf;
  }
  return std::uint32_t(all.size());
}

}  // namespace amalgam
