// The distributed layer (issue 28): MPI ranks across machines, the exec backends' threads inside
// each rank. `Comm` is the only place that calls MPI; built without MPI (AMALGAM_MPI=OFF or MPI
// not found) it is one rank and every collective is the identity, so callers need no #ifdef.
//
// Determinism: collectives used on floating-point state are exact (max, min, integer sums, and
// sums of doubles through ExactSum's integer words: sum_over_ranks) or move bytes (gather,
// all-to-all); no rank-count-dependent floating-point reduction is offered, because results must
// be bitwise the same on every rank count (docs/architecture.md).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/math/exact_sum.hpp"

namespace amalgam::dist {

bool mpi_built();  // whether this build has MPI (and Zoltan)

// Initialises MPI for the process's lifetime (MPI_THREAD_FUNNELED: only the calling thread makes
// MPI calls; the exec backends' threads never do) and finalises it when destroyed. Without MPI
// (or when not launched by mpirun) a single rank.
class Session {
 public:
  Session(int* argc, char*** argv);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;
};

class Comm {
 public:
  static Comm& world();
  int rank() const { return rank_; }
  int size() const { return size_; }
  bool root() const { return rank_ == 0; }
  // How many of the job's ranks share this rank's machine (MPI_COMM_TYPE_SHARED): what the
  // memory check before a run multiplies a rank's share by. One rank: 1.
  int node_ranks() const { return node_ranks_; }
  // Seconds this process spent in MPI_Init_thread (and Zoltan_Initialize): the set-up summary's
  // `mpi_init`. 0 without MPI or when not launched by mpirun.
  double init_seconds() const { return init_seconds_; }

  // The longest a rank waits in one collective for the others (seconds; `amalgam run
  // --comm-timeout`, default 600). A rank that waits longer prints which collective and which
  // peers it did not hear from and ends the job with exit code 1, so a dead or stuck peer never
  // leaves the others hanging.
  void set_timeout(double seconds) { timeout_ = seconds; }
  double timeout() const { return timeout_; }

  // What this rank's communication cost since the process started: the bytes it sent to other
  // ranks (payloads and the sizes that announce them), its messages (each point-to-point send to
  // another rank; a reduction, gather or broadcast counts one), its calls into Comm, and the wall
  // time spent inside them, waiting for slower ranks included. One rank: all zero.
  struct Traffic {
    std::uint64_t bytes = 0, messages = 0, calls = 0;
    double seconds = 0;
  };
  Traffic traffic() const { return traffic_; }

  double max(double v) const;
  double min(double v) const;
  std::uint64_t sum(std::uint64_t v) const;
  std::int64_t max(std::int64_t v) const;
  // Element by element (exact integer sums, in one reduction): ExactSum's words, for one.
  std::vector<std::int64_t> sum(const std::vector<std::int64_t>& v) const;
  // Element by element, in one reduction (several maxima at one synchronisation point).
  std::vector<double> max(const std::vector<double>& v) const;
  // Every rank's bytes, concatenated in rank order, on every rank (sizes[r]: rank r's count).
  std::vector<char> allgather(const std::vector<char>& mine, std::vector<std::size_t>* sizes) const;
  // Root only receives (others get an empty vector): every rank's bytes in rank order.
  std::vector<char> gather(const std::vector<char>& mine, std::vector<std::size_t>* sizes) const;
  // send[r]: the bytes for rank r (size() entries); returns recv[r]: the bytes from rank r.
  std::vector<std::vector<char>> alltoall(const std::vector<std::vector<char>>& send) const;
  // The same among `peers` only: sizes and bytes go to and come from those ranks, none from the
  // others, so the cost is O(|peers|), not O(size()). `peers` must be symmetric over the ranks
  // (r lists this rank exactly when this rank lists r; RcbCuts::neighbours) and send[r] empty
  // for every other rank r (std::logic_error otherwise, before anything is sent).
  std::vector<std::vector<char>> alltoall(const std::vector<std::vector<char>>& send,
                                          const std::vector<int>& peers) const;
  // Point to point (MPI_Isend/MPI_Irecv, no collective): send[r] goes to rank r when not empty;
  // recv_bytes[r] bytes are received from rank r when not zero (both sides know the pattern, as a
  // HaloPlan does). Returns recv[r]. Only the ranks that exchange bytes take part.
  std::vector<std::vector<char>> exchange(const std::vector<std::vector<char>>& send,
                                          const std::vector<std::size_t>& recv_bytes) const;
  // `exchange` in two halves, so that work runs while the bytes travel: exchange_start posts the
  // receives and the sends and returns at once; exchange_finish waits for the receives only and
  // returns recv[r]. The sends complete as the peers receive (OpenMPI's shared-memory and RDMA
  // transports let the receiver pull the bytes without the sender's help); `send` must stay
  // alive and unchanged until the Pending is started again or destroyed, which waits for them.
  class Pending {
   public:
    Pending();
    ~Pending();
    Pending(const Pending&) = delete;
    Pending& operator=(const Pending&) = delete;

   private:
    friend class Comm;
    struct State;
    std::unique_ptr<State> s_;
  };
  void exchange_start(Pending& p, const std::vector<std::vector<char>>& send,
                      const std::vector<std::size_t>& recv_bytes) const;
  std::vector<std::vector<char>> exchange_finish(Pending& p) const;
  // Root's bytes on every rank.
  void broadcast(std::vector<char>& bytes) const;
  void barrier() const;
  // Ends every rank of the job with this exit code (a fault on one rank must not leave the
  // others waiting in a collective). Single rank: std::exit.
  [[noreturn]] void abort(int code) const;

 private:
  friend class Session;
  Comm();
  void attach();  // reads the rank and size once MPI is initialised
  int rank_ = 0, size_ = 1, node_ranks_ = 1;
  double timeout_ = 600;
  double init_seconds_ = 0;
  mutable Traffic traffic_;
};

// Typed helpers over the byte collectives.
template <class T>
std::vector<char> as_bytes(const std::vector<T>& v) {
  const char* p = reinterpret_cast<const char*>(v.data());
  return std::vector<char>(p, p + v.size() * sizeof(T));
}
template <class T>
std::vector<T> from_bytes(const std::vector<char>& b) {
  std::vector<T> v(b.size() / sizeof(T));
  if (!v.empty())
    std::copy(b.data(), b.data() + v.size() * sizeof(T), reinterpret_cast<char*>(v.data()));
  return v;
}

// Recursive coordinate bisection of points by Zoltan (RCB, weighted): each rank passes its own
// points with their global ids; returns, for each of them, the rank that owns it. The partition
// depends on the input and the rank count only (Zoltan's RCB is deterministic), never on timing.
// Without MPI: every point on rank 0.
std::vector<int> partition_rcb(const std::vector<std::uint64_t>& ids,
                               const std::vector<double>& xyz, const std::vector<float>& weight,
                               double imbalance_tolerance = 1.05);

// Zoltan's RCB kept as its cuts (KEEP_CUTS): the owner of any point, also of a point that was not
// partitioned (Zoltan_LB_Point_Assign walks the cut tree, which every rank holds), the same on
// every rank. MPM leaves (solvers/mpm_distributed.cpp) are owned by the cut box their centre is
// in. Default, one rank or without MPI: every point on rank 0.
class RcbCuts {
 public:
  RcbCuts() = default;
  // Collective: partitions this rank's points (global ids, weights) and keeps the cuts.
  static RcbCuts partition(const std::vector<std::uint64_t>& ids, const std::vector<double>& xyz,
                           const std::vector<float>& weight, double imbalance_tolerance = 1.05);
  int owner(const double* p) const;  // local: no communication
  // The ranks whose cut regions meet the box [lo, hi] (Zoltan_LB_Box_Assign), local. Default:
  // rank 0.
  std::vector<int> ranks_in_box(const double* lo, const double* hi) const;
  // The other ranks whose cut regions come within `margin` of this rank's along every axis
  // (Zoltan_RCB_Box of every part, local): symmetric by construction, every rank applies the
  // same test to the same boxes. Sorted; empty on one rank.
  std::vector<int> neighbours(double margin) const;

 private:
  std::shared_ptr<void> zz_;  // the Zoltan_Struct holding the cuts
};

// The exact sums of every rank's accumulators, on every rank, in one integer reduction: the same
// bits on every rank count (core/math/exact_sum.hpp). One rank: unchanged.
inline void sum_over_ranks(const Comm& comm, ExactSum* sums, int n) {
  if (comm.size() == 1) return;
  std::vector<std::int64_t> w;
  w.reserve(std::size_t(n) * ExactSum::kWords);
  for (int i = 0; i < n; ++i) {
    const std::vector<std::int64_t> wi = sums[i].words();
    w.insert(w.end(), wi.begin(), wi.end());
  }
  w = comm.sum(w);
  for (int i = 0; i < n; ++i)
    sums[i] = ExactSum::from_words(
        std::vector<std::int64_t>(w.begin() + std::ptrdiff_t(i) * ExactSum::kWords,
                                  w.begin() + std::ptrdiff_t(i + 1) * ExactSum::kWords));
}

}  // namespace amalgam::dist
