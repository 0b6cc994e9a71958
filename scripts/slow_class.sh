#!/usr/bin/env bash
# Run a command the way the slower CPU class (x86 without VNNI, 2 cores) runs it, on any machine:
# one core, the CNN's self-check restricted to the 7-bit int8 kernels that class gets, and a
# background load on that core. `bash scripts/slow_class.sh bash scripts/test.sh test/test_x.py`.
# VMOCAP_SLOW_LOAD=0 leaves the background load out.
set -uo pipefail
core=${VMOCAP_SLOW_CORE:-0}
export VMOCAP_INT8_KERNELS=u8s8-w7
load_pid=""
if [ "${VMOCAP_SLOW_LOAD:-1}" != 0 ]; then
  # a busy loop that yields half of each 20 ms: about half the core left to the command
  taskset -c "$core" python3 -c '
import time
while True:
    t = time.perf_counter() + 0.01
    while time.perf_counter() < t:
        pass
    time.sleep(0.01)' &
  load_pid=$!
fi
trap '[ -n "$load_pid" ] && kill "$load_pid" 2>/dev/null' EXIT
taskset -c "$core" "$@"
