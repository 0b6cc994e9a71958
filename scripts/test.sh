#!/usr/bin/env bash
# Run the test suite with DDS discovery confined to this machine, inside a loopback-only
# network namespace when one can be created (root, or unprivileged user namespaces).
set -uo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYTHONUNBUFFERED=1
# Lint and type check first: a violation fails the run before any test starts
# (VMOCAP_TEST_LINT=0: tests only, for a second pass over the same tree).
lint_failed=0
if [ "${VMOCAP_TEST_LINT:-1}" = 0 ]; then
  :
elif ! .venv/bin/ruff check vmocap_core vmocap_ros test; then
  echo "test.sh: FAILED: ruff check vmocap_core vmocap_ros test" >&2
  lint_failed=1
fi
if [ "${VMOCAP_TEST_LINT:-1}" != 0 ] && ! .venv/bin/mypy vmocap_core; then
  echo "test.sh: FAILED: mypy vmocap_core" >&2
  lint_failed=1
fi
if [ "$lint_failed" -ne 0 ]; then
  exit 1
fi
run_pytest='.venv/bin/python -m pytest -q -p no:cacheprovider "$@"'
if unshare -n true 2>/dev/null; then
  echo "test.sh: running inside a loopback-only network namespace"
  unshare -n bash -c 'ip link set lo up && exec '"$run_pytest" bash "$@"
elif unshare -rn true 2>/dev/null; then
  echo "test.sh: running inside a loopback-only user+network namespace"
  unshare -rn bash -c 'ip link set lo up && exec '"$run_pytest" bash "$@"
else
  echo "test.sh: cannot create a network namespace; DDS discovery limited to localhost"
  eval "$run_pytest"
fi
