#include "core/dist/halo.hpp"

#include <algorithm>
#include <stdexcept>
#include <string>
#include <utility>

namespace amalgam::dist {

void HaloPlan::build(const std::vector<std::uint64_t>& owned_ids,
                     const std::vector<std::uint32_t>& owned_slots,
                     const std::vector<std::vector<std::uint64_t>>& want_from,
                     const std::vector<int>* peers) {
  const Comm& comm = Comm::world();
  std::vector<std::vector<char>> ask(want_from.size());
  for (std::size_t r = 0; r < want_from.size(); ++r) ask[r] = as_bytes(want_from[r]);
  const std::vector<std::vector<char>> asked =
      peers ? comm.alltoall(ask, *peers) : comm.alltoall(ask);
  // This rank's owned ids, sorted, to find each requested id's slot.
  std::vector<std::pair<std::uint64_t, std::uint32_t>> mine(owned_ids.size());
  for (std::size_t k = 0; k < owned_ids.size(); ++k) mine[k] = {owned_ids[k], owned_slots[k]};
  std::sort(mine.begin(), mine.end());
  send_.assign(asked.size(), {});
  for (std::size_t r = 0; r < asked.size(); ++r)
    for (std::uint64_t id : from_bytes<std::uint64_t>(asked[r])) {
      const auto it = std::lower_bound(mine.begin(), mine.end(),
                                       std::pair<std::uint64_t, std::uint32_t>(id, 0));
      if (it == mine.end() || it->first != id)
        throw std::runtime_error("halo: rank " + std::to_string(r) + " asked rank " +
                                 std::to_string(comm.rank()) + " for item " + std::to_string(id) +
                                 ", which it does not own");
      send_[r].push_back(it->second);
    }
}

void HaloPlan::exchange(void* data, std::size_t bytes) const {
  const Comm& comm = Comm::world();
  if (comm.size() == 1) return;
  char* base = static_cast<char*>(data);
  std::vector<std::vector<char>> out(send_.size());
  for (std::size_t r = 0; r < send_.size(); ++r) {
    out[r].resize(send_[r].size() * bytes);
    for (std::size_t k = 0; k < send_[r].size(); ++k)
      std::memcpy(out[r].data() + k * bytes, base + std::size_t(send_[r][k]) * bytes, bytes);
  }
  // Point to point: only the ranks that share ghosts exchange messages (both sides know the
  // sizes from the plan).
  std::vector<std::size_t> expect(recv_.size());
  for (std::size_t r = 0; r < recv_.size(); ++r) expect[r] = recv_[r].size() * bytes;
  const std::vector<std::vector<char>> in = comm.exchange(out, expect);
  for (std::size_t r = 0; r < recv_.size(); ++r) {
    if (in[r].size() != recv_[r].size() * bytes)
      throw std::runtime_error("halo: rank " + std::to_string(r) + " sent " +
                               std::to_string(in[r].size()) + " bytes, expected " +
                               std::to_string(recv_[r].size() * bytes));
    for (std::size_t k = 0; k < recv_[r].size(); ++k)
      std::memcpy(base + std::size_t(recv_[r][k]) * bytes, in[r].data() + k * bytes, bytes);
  }
}

std::size_t HaloPlan::messages() const {
  std::size_t n = 0;
  for (std::size_t r = 0; r < send_.size(); ++r)
    n += !send_[r].empty() && int(r) != Comm::world().rank();
  return n;
}

std::size_t HaloPlan::sent() const {
  std::size_t n = 0;
  for (const auto& s : send_) n += s.size();
  return n;
}

}  // namespace amalgam::dist
