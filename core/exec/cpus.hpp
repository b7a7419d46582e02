// How many CPUs the process has (core/exec/exec.cpp).
#pragma once

namespace amalgam::exec {

// The CPUs this process may run on: its affinity mask on Linux (what `nproc` prints; under
// mpirun a rank is bound to one core or socket by default), else the hardware threads
// (exec.hpp: hardware_threads). The default thread count of the commands.
int usable_threads();

}  // namespace amalgam::exec
