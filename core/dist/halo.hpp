// Ghost exchange by global id (issue 28): each rank owns some items (particles, or grid leaves)
// and keeps copies (ghosts) of items other ranks own. A HaloPlan is built once from who owns what
// and which ghosts each rank needs; exchange() then copies the owners' current values of any
// fixed-size attribute into the ghosts' slots. Values are moved as bytes, never combined, so a
// ghost holds exactly its owner's bits: a pass that reads ghosts gives the same result on every
// rank count.
#pragma once

#include <cstdint>
#include <cstring>
#include <vector>

#include "core/dist/comm.hpp"

namespace amalgam::dist {

class HaloPlan {
 public:
  HaloPlan() = default;
  // owned_ids: the global ids this rank owns, with their local slots; ghost_ids: the ids this
  // rank needs from others, with their local slots; owner_of(id) must know every ghost's owner.
  // Collective: every rank calls it. peers: when given, the requests go to those ranks only
  // (Comm::alltoall among peers; every ghost's owner must be one of them).
  template <class OwnerOf>
  HaloPlan(const std::vector<std::uint64_t>& owned_ids,
           const std::vector<std::uint32_t>& owned_slots,
           const std::vector<std::uint64_t>& ghost_ids,
           const std::vector<std::uint32_t>& ghost_slots, OwnerOf owner_of,
           const std::vector<int>* peers = nullptr);

  // Copies the owners' values of `data` (an array of records of `bytes` bytes, indexed by local
  // slot) into this rank's ghost slots. Point to point between the ranks that share ghosts
  // (Comm::exchange); every rank calls it.
  void exchange(void* data, std::size_t bytes) const;
  template <class T>
  void exchange(T* data) const {
    exchange(static_cast<void*>(data), sizeof(T));
  }

  std::size_t ghosts() const { return recv_slots_total_; }
  std::size_t sent() const;      // records this rank sends per exchange
  std::size_t messages() const;  // messages this rank sends per exchange (its neighbour ranks)

 private:
  void build(const std::vector<std::uint64_t>& owned_ids,
             const std::vector<std::uint32_t>& owned_slots,
             const std::vector<std::vector<std::uint64_t>>& want_from,
             const std::vector<int>* peers);
  // send_[r]: local slots whose values go to rank r, in the order rank r asked for them;
  // recv_[r]: local ghost slots filled from rank r, in the same order.
  std::vector<std::vector<std::uint32_t>> send_, recv_;
  std::size_t recv_slots_total_ = 0;
};

template <class OwnerOf>
HaloPlan::HaloPlan(const std::vector<std::uint64_t>& owned_ids,
                   const std::vector<std::uint32_t>& owned_slots,
                   const std::vector<std::uint64_t>& ghost_ids,
                   const std::vector<std::uint32_t>& ghost_slots, OwnerOf owner_of,
                   const std::vector<int>* peers) {
  const Comm& comm = Comm::world();
  std::vector<std::vector<std::uint64_t>> want(std::size_t(comm.size()));
  recv_.assign(std::size_t(comm.size()), {});
  for (std::size_t k = 0; k < ghost_ids.size(); ++k) {
    const int r = owner_of(ghost_ids[k]);
    want[std::size_t(r)].push_back(ghost_ids[k]);
    recv_[std::size_t(r)].push_back(ghost_slots[k]);
  }
  recv_slots_total_ = ghost_ids.size();
  build(owned_ids, owned_slots, want, peers);
}

}  // namespace amalgam::dist
