#include "core/dist/comm.hpp"

#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdlib>
#include <iostream>
#include <sstream>
#include <stdexcept>

#ifdef AMALGAM_HAVE_MPI
#include <mpi.h>
#include <trilinos/zoltan.h>
#endif

namespace amalgam::dist {

#ifdef AMALGAM_HAVE_MPI
bool mpi_built() {
  return true;
}

namespace {
bool g_initialized_here = false;
void check(int rc, const char* what) {
  if (rc != MPI_SUCCESS) throw std::runtime_error(std::string("MPI: ") + what + " failed");
}
// Counts and displacements of a variable-size exchange, as MPI's int counts (a message over 2 GB
// is refused rather than truncated).
std::vector<int> to_int_counts(const std::vector<std::size_t>& n) {
  std::vector<int> c(n.size());
  for (std::size_t i = 0; i < n.size(); ++i) {
    if (n[i] > std::size_t(2147483647)) throw std::runtime_error("MPI: a message over 2 GB");
    c[i] = int(n[i]);
  }
  return c;
}
std::vector<int> displacements(const std::vector<int>& c) {
  std::vector<int> d(c.size(), 0);
  long long s = 0;
  for (std::size_t i = 0; i < c.size(); ++i) {
    d[i] = int(s);
    s += c[i];
    if (s > 2147483647LL) throw std::runtime_error("MPI: an exchange over 2 GB");
  }
  return d;
}
// Waits for MPI requests against the rank's time-out (Comm::timeout): non-blocking operations
// polled with MPI_Testall, yielding the core after the first millisecond (ranks may share cores),
// and at once when this machine runs more ranks than it has hardware threads (an oversubscribed
// test or laptop run: a rank that spins holds the core the rank it waits for needs).
// `peer[k]`: the rank request k waits for (-1: a collective, whose missing ranks MPI does not
// name). On a time-out the rank says what it waited for and ends the job (exit 1): a peer that was
// killed or is stuck elsewhere must not leave the others waiting for ever.
// After a collective's time-out: which ranks are alive in Comm's waits. Every rank that timed
// out tells every other one so (point to point), then listens for a grace period (half the
// time-out, 1 to 30 s): the ranks not heard from are the ones stuck elsewhere or dead. The ranks
// waiting in one collective time out within the time they entered it apart.
std::vector<int> silent_ranks(double timeout) {
  constexpr int kAliveTag = 28099;
  const Comm& comm = Comm::world();
  const int R = comm.size(), me = comm.rank();
  static int token = 0;
  token = me;
  std::vector<MPI_Request> sends;
  for (int q = 0; q < R; ++q)
    if (q != me) {
      sends.emplace_back();
      MPI_Isend(&token, 1, MPI_INT, q, kAliveTag, MPI_COMM_WORLD, &sends.back());
    }
  std::vector<char> heard(std::size_t(R), 0);
  heard[std::size_t(me)] = 1;
  int count = 1;
  const double grace = std::min(30.0, std::max(1.0, 0.5 * timeout));
  const auto t0 = std::chrono::steady_clock::now();
  while (count < R &&
         std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < grace) {
    int flag = 0;
    MPI_Status st;
    MPI_Iprobe(MPI_ANY_SOURCE, kAliveTag, MPI_COMM_WORLD, &flag, &st);
    if (!flag) {
      ::usleep(1000);
      continue;
    }
    int v = 0;
    MPI_Recv(&v, 1, MPI_INT, st.MPI_SOURCE, kAliveTag, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
    if (!heard[std::size_t(st.MPI_SOURCE)]) heard[std::size_t(st.MPI_SOURCE)] = 1, ++count;
  }
  std::vector<int> silent;
  for (int q = 0; q < R; ++q)
    if (!heard[std::size_t(q)]) silent.push_back(q);
  return silent;
}

// Counts one call into Comm (Comm::traffic): its bytes and messages now, its time when it returns.
class Meter {
 public:
  Meter(Comm::Traffic& t, std::uint64_t bytes, std::uint64_t messages)
      : t_(t), t0_(std::chrono::steady_clock::now()) {
    t_.bytes += bytes, t_.messages += messages, ++t_.calls;
  }
  ~Meter() {
    t_.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
  }
  Meter(const Meter&) = delete;
  Meter& operator=(const Meter&) = delete;

 private:
  Comm::Traffic& t_;
  std::chrono::steady_clock::time_point t0_;
};

void wait_all(std::vector<MPI_Request>& req, const std::vector<int>& peer, const char* what) {
  if (req.empty()) return;
  const Comm& comm = Comm::world();
  const auto t0 = std::chrono::steady_clock::now();
  static const bool sharing =
      comm.node_ranks() > int(std::max(1L, ::sysconf(_SC_NPROCESSORS_ONLN)));
  for (long long polls = 0;; ++polls) {
    int done = 0;
    check(MPI_Testall(int(req.size()), req.data(), &done, MPI_STATUSES_IGNORE), what);
    if (done) return;
    const double waited =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (waited > comm.timeout()) {
      std::ostringstream m;
      m << "amalgam: error: MPI rank " << comm.rank() << " of " << comm.size() << ": no answer in "
        << what << " within " << comm.timeout() << " s (--comm-timeout): ";
      std::vector<int> missing;
      bool collective = false;
      for (std::size_t k = 0; k < req.size(); ++k) {
        int ok = 1;
        if (req[k] != MPI_REQUEST_NULL) check(MPI_Test(&req[k], &ok, MPI_STATUS_IGNORE), what);
        if (!ok && peer[k] < 0) collective = true;
        if (!ok && peer[k] >= 0 &&
            std::find(missing.begin(), missing.end(), peer[k]) == missing.end())
          missing.push_back(peer[k]);
      }
      if (!missing.empty()) {
        m << "did not hear from rank" << (missing.size() > 1 ? "s" : "");
        for (std::size_t k = 0; k < missing.size(); ++k) m << (k ? ", " : " ") << missing[k];
      } else if (collective) {
        const std::vector<int> silent = silent_ranks(comm.timeout());
        if (silent.empty()) {
          m << "not every rank joined this collective, yet every rank answered afterwards";
        } else {
          m << "not every rank joined this collective; did not hear from rank"
            << (silent.size() > 1 ? "s" : "");
          for (std::size_t k = 0; k < silent.size(); ++k) m << (k ? ", " : " ") << silent[k];
          m << " (killed, or stuck outside Amalgam's exchanges)";
        }
      }
      m << "; ending every rank\n";
      std::cerr << m.str();
      std::cerr.flush();
      MPI_Abort(MPI_COMM_WORLD, 1);
      std::exit(1);
    }
    if (sharing)
      ::sched_yield();
    else if (polls > 1000 && waited > 1e-3)
      ::usleep(50);
  }
}
void wait_one(MPI_Request r, const char* what) {
  std::vector<MPI_Request> req{r};
  wait_all(req, {-1}, what);
}
// Whether a launcher (mpirun, mpiexec, srun) started this process: only then is MPI initialised,
// so a plain `amalgam run` never pays for (or depends on) MPI's start-up, and OpenMPI's singleton
// start, which would fork a daemon, never happens.
bool launched_by_mpi() {
  for (const char* v : {"OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_SIZE", "PMI_RANK"})
    if (std::getenv(v)) return true;
  return false;
}
}  // namespace

Session::Session(int* argc, char*** argv) {
  if (!launched_by_mpi()) return;
  int done = 0;
  MPI_Initialized(&done);
  const auto t0 = std::chrono::steady_clock::now();
  if (!done) {
    int provided = 0;
    check(MPI_Init_thread(argc, argv, MPI_THREAD_FUNNELED, &provided), "MPI_Init_thread");
    g_initialized_here = true;
    float version = 0;
    Zoltan_Initialize(argc ? *argc : 0, argv ? *argv : nullptr, &version);
  }
  Comm::world().attach();
  Comm::world().init_seconds_ =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
Session::~Session() {
  int finalized = 0;
  MPI_Finalized(&finalized);
  if (g_initialized_here && !finalized) MPI_Finalize();
}

Comm::Comm() {
  attach();
}
void Comm::attach() {
  int init = 0;
  MPI_Initialized(&init);
  if (!init) return;  // used before (or without) a Session: one rank
  MPI_Comm_rank(MPI_COMM_WORLD, &rank_);
  MPI_Comm_size(MPI_COMM_WORLD, &size_);
  MPI_Comm node;
  if (MPI_Comm_split_type(MPI_COMM_WORLD, MPI_COMM_TYPE_SHARED, rank_, MPI_INFO_NULL, &node) ==
      MPI_SUCCESS) {
    MPI_Comm_size(node, &node_ranks_);
    MPI_Comm_free(&node);
  }
}

double Comm::max(double v) const {
  if (size_ == 1) return v;
  const Meter meter(traffic_, sizeof v, 1);
  double r = v;
  MPI_Request q;
  check(MPI_Iallreduce(&v, &r, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD, &q), "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (max)");
  return r;
}
double Comm::min(double v) const {
  if (size_ == 1) return v;
  const Meter meter(traffic_, sizeof v, 1);
  double r = v;
  MPI_Request q;
  check(MPI_Iallreduce(&v, &r, 1, MPI_DOUBLE, MPI_MIN, MPI_COMM_WORLD, &q), "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (min)");
  return r;
}
std::uint64_t Comm::sum(std::uint64_t v) const {
  if (size_ == 1) return v;
  const Meter meter(traffic_, sizeof v, 1);
  std::uint64_t r = v;
  MPI_Request q;
  check(MPI_Iallreduce(&v, &r, 1, MPI_UINT64_T, MPI_SUM, MPI_COMM_WORLD, &q), "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (sum)");
  return r;
}
std::int64_t Comm::max(std::int64_t v) const {
  if (size_ == 1) return v;
  const Meter meter(traffic_, sizeof v, 1);
  std::int64_t r = v;
  MPI_Request q;
  check(MPI_Iallreduce(&v, &r, 1, MPI_INT64_T, MPI_MAX, MPI_COMM_WORLD, &q), "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (max)");
  return r;
}
std::vector<std::int64_t> Comm::sum(const std::vector<std::int64_t>& v) const {
  if (size_ == 1 || v.empty()) return v;
  const Meter meter(traffic_, v.size() * sizeof(std::int64_t), 1);
  std::vector<std::int64_t> r(v.size());
  MPI_Request q;
  check(MPI_Iallreduce(v.data(), r.data(), int(v.size()), MPI_INT64_T, MPI_SUM, MPI_COMM_WORLD, &q),
        "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (sum)");
  return r;
}
std::vector<double> Comm::max(const std::vector<double>& v) const {
  if (size_ == 1 || v.empty()) return v;
  const Meter meter(traffic_, v.size() * sizeof(double), 1);
  std::vector<double> r(v.size());
  MPI_Request q;
  check(MPI_Iallreduce(v.data(), r.data(), int(v.size()), MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD, &q),
        "MPI_Iallreduce");
  wait_one(q, "MPI_Iallreduce (max)");
  return r;
}

std::vector<char> Comm::allgather(const std::vector<char>& mine,
                                  std::vector<std::size_t>* sizes) const {
  if (size_ == 1) {
    if (sizes) *sizes = {mine.size()};
    return mine;
  }
  const Meter meter(traffic_, mine.size() + sizeof(int), 2);
  const std::vector<int> one = to_int_counts({mine.size()});
  std::vector<int> counts(static_cast<std::size_t>(size_), 0);
  MPI_Request q;
  check(MPI_Iallgather(&one[0], 1, MPI_INT, counts.data(), 1, MPI_INT, MPI_COMM_WORLD, &q),
        "MPI_Iallgather");
  wait_one(q, "MPI_Iallgather (sizes)");
  const std::vector<int> displ = displacements(counts);
  std::vector<char> all(std::size_t(displ.back()) + std::size_t(counts.back()));
  check(MPI_Iallgatherv(mine.data(), one[0], MPI_BYTE, all.data(), counts.data(), displ.data(),
                        MPI_BYTE, MPI_COMM_WORLD, &q),
        "MPI_Iallgatherv");
  wait_one(q, "MPI_Iallgatherv");
  if (sizes) sizes->assign(counts.begin(), counts.end());
  return all;
}

std::vector<char> Comm::gather(const std::vector<char>& mine,
                               std::vector<std::size_t>* sizes) const {
  if (size_ == 1) {
    if (sizes) *sizes = {mine.size()};
    return mine;
  }
  const Meter meter(traffic_, rank_ == 0 ? 0 : mine.size() + sizeof(int), rank_ == 0 ? 0 : 2);
  const std::vector<int> one = to_int_counts({mine.size()});
  std::vector<int> counts(static_cast<std::size_t>(size_), 0);
  MPI_Request q;
  check(MPI_Igather(&one[0], 1, MPI_INT, counts.data(), 1, MPI_INT, 0, MPI_COMM_WORLD, &q),
        "MPI_Igather");
  wait_one(q, "MPI_Igather (sizes)");
  std::vector<char> all;
  std::vector<int> displ(static_cast<std::size_t>(size_), 0);
  if (rank_ == 0) {
    displ = displacements(counts);
    all.resize(std::size_t(displ.back()) + std::size_t(counts.back()));
  }
  check(MPI_Igatherv(mine.data(), one[0], MPI_BYTE, all.data(), counts.data(), displ.data(),
                     MPI_BYTE, 0, MPI_COMM_WORLD, &q),
        "MPI_Igatherv");
  wait_one(q, "MPI_Igatherv");
  if (sizes) sizes->assign(counts.begin(), counts.end());
  return all;
}

std::vector<std::vector<char>> Comm::alltoall(const std::vector<std::vector<char>>& send) const {
  std::vector<int> others;
  for (int r = 0; r < size_; ++r)
    if (r != rank_) others.push_back(r);
  return alltoall(send, others);
}

std::vector<std::vector<char>> Comm::alltoall(const std::vector<std::vector<char>>& send,
                                              const std::vector<int>& peers) const {
  if (size_ == 1) return send;
  // Point to point (sizes, then bytes), so a time-out can name the peers that did not answer.
  // Messages between two ranks stay in order (MPI's non-overtaking rule), and every rank makes
  // the same sequence of calls, so tags need not count.
  constexpr int kSizeTag = 28001, kDataTag = 28002;
  const std::size_t R = std::size_t(size_), me = std::size_t(rank_);
  std::vector<char> is_peer(R, 0);
  for (int r : peers) is_peer[std::size_t(r)] = 1;
  std::uint64_t payload = 0, sends = peers.size();
  for (std::size_t r = 0; r < R; ++r) {
    if (r == me || send[r].empty()) continue;
    if (!is_peer[r])
      throw std::logic_error("MPI: rank " + std::to_string(rank_) + " has bytes for rank " +
                             std::to_string(r) + ", which is not one of its exchange peers");
    payload += send[r].size(), ++sends;
  }
  const Meter meter(traffic_, payload + peers.size() * sizeof(std::uint64_t), sends);
  std::vector<std::uint64_t> out_n(R), in_n(R, 0);
  std::vector<MPI_Request> req;
  std::vector<int> peer;
  for (std::size_t r = 0; r < R; ++r) {
    out_n[r] = send[r].size();
    if (out_n[r] > std::uint64_t(2147483647)) throw std::runtime_error("MPI: a message over 2 GB");
  }
  for (int r : peers) {
    req.emplace_back();
    peer.push_back(r);
    check(
        MPI_Irecv(&in_n[std::size_t(r)], 1, MPI_UINT64_T, r, kSizeTag, MPI_COMM_WORLD, &req.back()),
        "MPI_Irecv");
  }
  for (int r : peers) {
    req.emplace_back();
    peer.push_back(r);
    check(MPI_Isend(&out_n[std::size_t(r)], 1, MPI_UINT64_T, r, kSizeTag, MPI_COMM_WORLD,
                    &req.back()),
          "MPI_Isend");
  }
  wait_all(req, peer, "the all-to-all exchange (sizes)");
  std::vector<std::vector<char>> recv(R);
  recv[me] = send[me];
  req.clear();
  peer.clear();
  for (int r : peers) {
    const std::size_t q = std::size_t(r);
    if (in_n[q] > std::uint64_t(2147483647)) throw std::runtime_error("MPI: a message over 2 GB");
    recv[q].resize(std::size_t(in_n[q]));
    if (in_n[q] == 0) continue;
    req.emplace_back();
    peer.push_back(r);
    check(
        MPI_Irecv(recv[q].data(), int(in_n[q]), MPI_BYTE, r, kDataTag, MPI_COMM_WORLD, &req.back()),
        "MPI_Irecv");
  }
  for (int r : peers) {
    const std::size_t q = std::size_t(r);
    if (out_n[q] == 0) continue;
    req.emplace_back();
    peer.push_back(r);
    check(MPI_Isend(send[q].data(), int(out_n[q]), MPI_BYTE, r, kDataTag, MPI_COMM_WORLD,
                    &req.back()),
          "MPI_Isend");
  }
  wait_all(req, peer, "the all-to-all exchange (bytes)");
  return recv;
}

struct Comm::Pending::State {
  std::vector<std::vector<char>> recv;
  std::vector<MPI_Request> recv_req, send_req;
  std::vector<int> recv_peer, send_peer;
  void wait_sends() {
    wait_all(send_req, send_peer, "the halo exchange (sends)");
    send_req.clear(), send_peer.clear();
  }
};
Comm::Pending::Pending() : s_(std::make_unique<State>()) {}
Comm::Pending::~Pending() {
  int finalized = 0;
  MPI_Finalized(&finalized);
  if (!finalized && !s_->send_req.empty()) s_->wait_sends();
}

void Comm::exchange_start(Pending& p, const std::vector<std::vector<char>>& send,
                          const std::vector<std::size_t>& recv_bytes) const {
  Pending::State& st = *p.s_;
  st.wait_sends();  // the previous start's: its buffers may be reused now
  st.recv.assign(static_cast<std::size_t>(size_), {});
  st.recv_req.clear(), st.recv_peer.clear();
  if (size_ == 1) {
    st.recv = send;
    return;
  }
  std::uint64_t payload = 0, sends = 0;
  for (std::size_t r = 0; r < send.size(); ++r)
    if (int(r) != rank_ && !send[r].empty()) payload += send[r].size(), ++sends;
  const Meter meter(traffic_, payload, sends);
  const std::vector<int> rc = to_int_counts(recv_bytes);
  std::vector<std::size_t> sn(send.size());
  for (std::size_t r = 0; r < send.size(); ++r) sn[r] = send[r].size();
  const std::vector<int> sc = to_int_counts(sn);
  for (int r = 0; r < size_; ++r) {
    if (rc[std::size_t(r)] == 0) continue;
    st.recv[std::size_t(r)].resize(recv_bytes[std::size_t(r)]);
    st.recv_req.emplace_back();
    st.recv_peer.push_back(r);
    check(MPI_Irecv(st.recv[std::size_t(r)].data(), rc[std::size_t(r)], MPI_BYTE, r, 28,
                    MPI_COMM_WORLD, &st.recv_req.back()),
          "MPI_Irecv");
  }
  for (int r = 0; r < size_; ++r) {
    if (sc[std::size_t(r)] == 0) continue;
    st.send_req.emplace_back();
    st.send_peer.push_back(r);
    check(MPI_Isend(send[std::size_t(r)].data(), sc[std::size_t(r)], MPI_BYTE, r, 28,
                    MPI_COMM_WORLD, &st.send_req.back()),
          "MPI_Isend");
  }
}

std::vector<std::vector<char>> Comm::exchange_finish(Pending& p) const {
  Pending::State& st = *p.s_;
  if (!st.recv_req.empty()) {
    const auto t0 = std::chrono::steady_clock::now();
    wait_all(st.recv_req, st.recv_peer, "the halo exchange");
    traffic_.seconds +=
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  st.recv_req.clear(), st.recv_peer.clear();
  return std::move(st.recv);
}

std::vector<std::vector<char>> Comm::exchange(const std::vector<std::vector<char>>& send,
                                              const std::vector<std::size_t>& recv_bytes) const {
  if (size_ == 1) return send;
  Pending p;
  exchange_start(p, send, recv_bytes);
  std::vector<std::vector<char>> recv = exchange_finish(p);
  const Meter meter(traffic_, 0, 0);
  --traffic_.calls;  // one call: exchange_start counted it
  p.s_->wait_sends();
  return recv;
}

void Comm::broadcast(std::vector<char>& bytes) const {
  if (size_ == 1) return;
  const Meter meter(traffic_, rank_ == 0 ? bytes.size() + 8 : 0, rank_ == 0 ? 2 : 0);
  std::uint64_t n = bytes.size();
  MPI_Request q;
  check(MPI_Ibcast(&n, 1, MPI_UINT64_T, 0, MPI_COMM_WORLD, &q), "MPI_Ibcast");
  wait_one(q, "MPI_Ibcast (size)");
  if (n > 2147483647ULL) throw std::runtime_error("MPI: a broadcast over 2 GB");
  bytes.resize(std::size_t(n));
  check(MPI_Ibcast(bytes.data(), int(n), MPI_BYTE, 0, MPI_COMM_WORLD, &q), "MPI_Ibcast");
  wait_one(q, "MPI_Ibcast");
}

void Comm::barrier() const {
  if (size_ == 1) return;
  const Meter meter(traffic_, 0, 1);
  MPI_Request q;
  check(MPI_Ibarrier(MPI_COMM_WORLD, &q), "MPI_Ibarrier");
  wait_one(q, "MPI_Ibarrier");
}

void Comm::abort(int code) const {
  if (size_ > 1) MPI_Abort(MPI_COMM_WORLD, code);
  std::exit(code);
}

namespace {
struct RcbInput {
  const std::vector<std::uint64_t>* ids;
  const std::vector<double>* xyz;
  const std::vector<float>* weight;
};
int num_obj(void* data, int* ierr) {
  *ierr = ZOLTAN_OK;
  return int(static_cast<RcbInput*>(data)->ids->size());
}
void obj_list(void* data, int, int, ZOLTAN_ID_PTR gids, ZOLTAN_ID_PTR lids, int wdim, float* w,
              int* ierr) {
  const RcbInput& in = *static_cast<RcbInput*>(data);
  for (std::size_t i = 0; i < in.ids->size(); ++i) {
    gids[i] = ZOLTAN_ID_TYPE((*in.ids)[i]);
    lids[i] = ZOLTAN_ID_TYPE(i);
    if (wdim > 0) w[i] = (*in.weight)[i];
  }
  *ierr = ZOLTAN_OK;
}
int num_geom(void*, int* ierr) {
  *ierr = ZOLTAN_OK;
  return 3;
}
void geom_multi(void* data, int, int, int n, ZOLTAN_ID_PTR, ZOLTAN_ID_PTR lids, int dim,
                double* geom, int* ierr) {
  const RcbInput& in = *static_cast<RcbInput*>(data);
  for (int k = 0; k < n; ++k)
    for (int a = 0; a < dim; ++a) geom[k * dim + a] = (*in.xyz)[std::size_t(lids[k]) * 3 + a];
  *ierr = ZOLTAN_OK;
}
}  // namespace

namespace {
// A Zoltan RCB partition of the points; `keep_cuts`: the cuts stay in the returned struct (for
// Zoltan_LB_Point_Assign). exp: this rank's points that move, as (local index, new rank).
Zoltan_Struct* run_rcb(const std::vector<std::uint64_t>& ids, const std::vector<double>& xyz,
                       const std::vector<float>& weight, double imbalance_tolerance, bool keep_cuts,
                       std::vector<std::pair<std::size_t, int>>* exp) {
  if (sizeof(ZOLTAN_ID_TYPE) < sizeof(std::uint32_t))
    throw std::runtime_error("Zoltan: its id type is too small");
  for (std::uint64_t id : ids)
    if (id > std::uint64_t(ZOLTAN_ID_TYPE(-1)))
      throw std::runtime_error("Zoltan: a global id beyond its id type (build with 64-bit ids)");
  RcbInput in{&ids, &xyz, &weight};
  Zoltan_Struct* zz = Zoltan_Create(MPI_COMM_WORLD);
  if (!zz) throw std::runtime_error("Zoltan_Create failed");
  Zoltan_Set_Param(zz, "DEBUG_LEVEL", "0");  // first: setting the method prints at level 1
  Zoltan_Set_Param(zz, "LB_METHOD", "RCB");
  Zoltan_Set_Param(zz, "NUM_GID_ENTRIES", "1");
  Zoltan_Set_Param(zz, "NUM_LID_ENTRIES", "1");
  // Weighted when any rank has weights: a rank with no points has none, and Zoltan's reductions
  // need the same weight dimension on every rank.
  const bool weighted = Comm::world().max(std::int64_t(!weight.empty())) > 0;
  Zoltan_Set_Param(zz, "OBJ_WEIGHT_DIM", weighted ? "1" : "0");
  Zoltan_Set_Param(zz, "RETURN_LISTS", "EXPORT");
  Zoltan_Set_Param(zz, "KEEP_CUTS", keep_cuts ? "1" : "0");
  Zoltan_Set_Param(zz, "RCB_REUSE", "0");
  Zoltan_Set_Param(zz, "AVERAGE_CUTS",
                   "1");  // cuts midway between points: away from lattice planes
  const std::string tol = std::to_string(imbalance_tolerance);
  Zoltan_Set_Param(zz, "IMBALANCE_TOL", tol.c_str());
  Zoltan_Set_Num_Obj_Fn(zz, num_obj, &in);
  Zoltan_Set_Obj_List_Fn(zz, obj_list, &in);
  Zoltan_Set_Num_Geom_Fn(zz, num_geom, &in);
  Zoltan_Set_Geom_Multi_Fn(zz, geom_multi, &in);
  int changes = 0, ngid = 0, nlid = 0, nimp = 0, nexp = 0;
  ZOLTAN_ID_PTR imp_g = nullptr, imp_l = nullptr, exp_g = nullptr, exp_l = nullptr;
  int *imp_p = nullptr, *imp_to = nullptr, *exp_p = nullptr, *exp_to = nullptr;
  const int rc = Zoltan_LB_Partition(zz, &changes, &ngid, &nlid, &nimp, &imp_g, &imp_l, &imp_p,
                                     &imp_to, &nexp, &exp_g, &exp_l, &exp_p, &exp_to);
  if ((rc == ZOLTAN_OK || rc == ZOLTAN_WARN) && exp)
    for (int k = 0; k < nexp; ++k) exp->push_back({std::size_t(exp_l[k]), exp_p[k]});
  Zoltan_LB_Free_Part(&imp_g, &imp_l, &imp_p, &imp_to);
  Zoltan_LB_Free_Part(&exp_g, &exp_l, &exp_p, &exp_to);
  if (rc != ZOLTAN_OK && rc != ZOLTAN_WARN) {
    Zoltan_Destroy(&zz);
    throw std::runtime_error("Zoltan_LB_Partition (RCB) failed with code " + std::to_string(rc));
  }
  return zz;
}
}  // namespace

std::vector<int> partition_rcb(const std::vector<std::uint64_t>& ids,
                               const std::vector<double>& xyz, const std::vector<float>& weight,
                               double imbalance_tolerance) {
  const Comm& comm = Comm::world();
  std::vector<int> owner(ids.size(), comm.rank());
  if (comm.size() == 1) return owner;
  std::vector<std::pair<std::size_t, int>> exp;
  Zoltan_Struct* zz = run_rcb(ids, xyz, weight, imbalance_tolerance, false, &exp);
  Zoltan_Destroy(&zz);
  for (const auto& e : exp) owner[e.first] = e.second;
  return owner;
}

RcbCuts RcbCuts::partition(const std::vector<std::uint64_t>& ids, const std::vector<double>& xyz,
                           const std::vector<float>& weight, double imbalance_tolerance) {
  RcbCuts c;
  if (Comm::world().size() == 1) return c;
  Zoltan_Struct* zz = run_rcb(ids, xyz, weight, imbalance_tolerance, true, nullptr);
  c.zz_ = std::shared_ptr<void>(zz, [](void* z) {
    Zoltan_Struct* p = static_cast<Zoltan_Struct*>(z);
    Zoltan_Destroy(&p);
  });
  return c;
}

int RcbCuts::owner(const double* p) const {
  if (!zz_) return 0;
  double q[3] = {p[0], p[1], p[2]};
  int proc = 0;
  if (Zoltan_LB_Point_Assign(static_cast<Zoltan_Struct*>(zz_.get()), q, &proc) != ZOLTAN_OK)
    throw std::runtime_error("Zoltan_LB_Point_Assign failed");
  return proc;
}

std::vector<int> RcbCuts::ranks_in_box(const double* lo, const double* hi) const {
  if (!zz_) return {0};
  std::vector<int> procs(std::size_t(Comm::world().size()));
  int n = 0;
  if (Zoltan_LB_Box_Assign(static_cast<Zoltan_Struct*>(zz_.get()), lo[0], lo[1], lo[2], hi[0],
                           hi[1], hi[2], procs.data(), &n) != ZOLTAN_OK)
    throw std::runtime_error("Zoltan_LB_Box_Assign failed");
  procs.resize(std::size_t(n));
  return procs;
}

std::vector<int> RcbCuts::neighbours(double margin) const {
  if (!zz_) return {};
  Zoltan_Struct* zz = static_cast<Zoltan_Struct*>(zz_.get());
  const int R = Comm::world().size(), me = Comm::world().rank();
  std::vector<std::array<double, 6>> box(static_cast<std::size_t>(R));
  for (int r = 0; r < R; ++r) {
    int nd = 0;
    double* b = box[std::size_t(r)].data();
    if (Zoltan_RCB_Box(zz, r, &nd, &b[0], &b[1], &b[2], &b[3], &b[4], &b[5]) != ZOLTAN_OK)
      throw std::runtime_error("Zoltan_RCB_Box failed for part " + std::to_string(r));
  }
  const std::array<double, 6>& m = box[std::size_t(me)];
  std::vector<int> out;
  for (int r = 0; r < R; ++r) {
    if (r == me) continue;
    const std::array<double, 6>& o = box[std::size_t(r)];
    bool near = true;
    for (int a = 0; a < 3; ++a)
      near = near && o[std::size_t(a)] <= m[std::size_t(a) + 3] + margin &&
             m[std::size_t(a)] <= o[std::size_t(a) + 3] + margin;
    if (near) out.push_back(r);
  }
  return out;
}

#else  // no MPI: one rank

bool mpi_built() {
  return false;
}
Session::Session(int*, char***) {}
Session::~Session() = default;
Comm::Comm() = default;
void Comm::attach() {}
double Comm::max(double v) const {
  return v;
}
double Comm::min(double v) const {
  return v;
}
std::uint64_t Comm::sum(std::uint64_t v) const {
  return v;
}
std::int64_t Comm::max(std::int64_t v) const {
  return v;
}
std::vector<std::int64_t> Comm::sum(const std::vector<std::int64_t>& v) const {
  return v;
}
std::vector<double> Comm::max(const std::vector<double>& v) const {
  return v;
}
std::vector<char> Comm::allgather(const std::vector<char>& mine,
                                  std::vector<std::size_t>* sizes) const {
  if (sizes) *sizes = {mine.size()};
  return mine;
}
std::vector<char> Comm::gather(const std::vector<char>& mine,
                               std::vector<std::size_t>* sizes) const {
  if (sizes) *sizes = {mine.size()};
  return mine;
}
std::vector<std::vector<char>> Comm::alltoall(const std::vector<std::vector<char>>& send) const {
  return send;
}
std::vector<std::vector<char>> Comm::alltoall(const std::vector<std::vector<char>>& send,
                                              const std::vector<int>&) const {
  return send;
}
std::vector<std::vector<char>> Comm::exchange(const std::vector<std::vector<char>>& send,
                                              const std::vector<std::size_t>&) const {
  return send;
}
struct Comm::Pending::State {
  std::vector<std::vector<char>> recv;
};
Comm::Pending::Pending() : s_(std::make_unique<State>()) {}
Comm::Pending::~Pending() = default;
void Comm::exchange_start(Pending& p, const std::vector<std::vector<char>>& send,
                          const std::vector<std::size_t>&) const {
  p.s_->recv = send;
}
std::vector<std::vector<char>> Comm::exchange_finish(Pending& p) const {
  return std::move(p.s_->recv);
}
void Comm::broadcast(std::vector<char>&) const {}
void Comm::barrier() const {}
void Comm::abort(int code) const {
  std::exit(code);
}
std::vector<int> partition_rcb(const std::vector<std::uint64_t>& ids, const std::vector<double>&,
                               const std::vector<float>&, double) {
  return std::vector<int>(ids.size(), 0);
}
RcbCuts RcbCuts::partition(const std::vector<std::uint64_t>&, const std::vector<double>&,
                           const std::vector<float>&, double) {
  return RcbCuts();
}
int RcbCuts::owner(const double*) const {
  return 0;
}
std::vector<int> RcbCuts::ranks_in_box(const double*, const double*) const {
  return {0};
}
std::vector<int> RcbCuts::neighbours(double) const {
  return {};
}

#endif

Comm& Comm::world() {
  static Comm c;
  return c;
}

}  // namespace amalgam::dist
