#!/usr/bin/env bash
# The test command (README): install what the tests need, lint, type-check, run the tests
# (the full suite, on python3: 3.11 here), then the Python x ROS 2 matrix (scripts/test_matrix.sh:
# the SDK, server, wire, CLI and ROS 2 tests on Python 3.10, 3.12 and 3.13, ROS 2 Jazzy's wheels
# and a graph across releases, the README's examples after a plain `pip install .` on each
# Python). Works on a fresh machine with only Python 3.11, pip and apt: a Python that is not
# there is a loud MISSING line and its legs are skipped, except with CI=true, where it fails.
# Extra args go to the full suite's pytest.
set -euo pipefail
cd "$(dirname "$0")/.."

# System tools for the network-emulator and stress tests. Without root they are skipped,
# and the tests that need them skip with the reason printed.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  need=()
  command -v ip >/dev/null 2>&1 || need+=(iproute2)
  command -v nft >/dev/null 2>&1 || need+=(nftables)
  command -v stress >/dev/null 2>&1 || need+=(stress)
  [ -e /usr/include/sodium.h ] || need+=(libsodium-dev)  # setup.py builds the cipher with it
  if [ "${#need[@]}" -gt 0 ]; then
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
  fi
fi

# -- the C client (clients/c, issue 28): its build tools and libraries -----------------------
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  c_need=()
  command -v cmake >/dev/null 2>&1 || c_need+=(cmake)
  command -v cc >/dev/null 2>&1 || c_need+=(gcc)
  [ -e /usr/include/msgpack.h ] || c_need+=(libmsgpack-dev)
  [ -e /usr/include/cmocka.h ] || c_need+=(libcmocka-dev)
  [ -e /usr/include/sodium.h ] || c_need+=(libsodium-dev)
  [ -e /usr/include/openssl/ssl.h ] || c_need+=(libssl-dev)  # its TLS sessions
  if [ "${#c_need[@]}" -gt 0 ]; then
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${c_need[@]}" >/dev/null
  fi
fi

python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test,ros2,compare]"

.venv/bin/ruff check src tests scripts benchmarks examples setup.py
.venv/bin/mypy --strict src benchmarks
# pytest exits 5 when it collected no test: that fails the run, as it should. The matrix runs
# after a failed suite too (one CI run shows both); the run fails if either failed.
export RLBRIDGE_TEST_REQUIRE_ROS2=1  # rclpy was installed above: the ROS 2 tests must run
# The install above compiled the value path (setup.py) unless RLBRIDGE_PURE_PYTHON was set: the
# tests of the compiled modules must run, not skip (tests/packaging/test_compiled.py).
[ -n "${RLBRIDGE_PURE_PYTHON:-}" ] || export RLBRIDGE_TEST_REQUIRE_COMPILED=1
# -- the C client: built warning-free (-Werror, gcc and clang where installed), its unit
# tests (ctest: protocol.md 16.6 vectors, the decoder), then tests/c_client must run, not skip.
cmake -S clients/c -B build/c -DRLB_WERROR=ON >/dev/null
cmake --build build/c -j 2 >/dev/null
(cd build/c && ctest --output-on-failure)
if command -v clang >/dev/null 2>&1; then
  CC=clang cmake -S clients/c -B build/c-clang -DRLB_WERROR=ON >/dev/null
  cmake --build build/c-clang -j 2 >/dev/null
fi
# -- the C client's hardening (issue 28, point 7): the library, the fuzz corpus's harness
# (clients/c/tests/fuzz_decode.c: fuzz/corpus and 20000 mutated and random inputs through the
# receive path, the handshake) and the unit tests (the failing allocator's leaks included) built
# with AddressSanitizer and UndefinedBehaviorSanitizer into build/c-asan; the first report
# aborts and fails the run. The seccomp proof of the real-time rule (point 6) is
# tests/c_client/test_c_realtime.py, in the suite.
cmake -S clients/c -B build/c-asan -DRLB_SANITIZE=ON -DRLB_WERROR=ON -DRLB_FUZZ_RANDOM=20000 >/dev/null
cmake --build build/c-asan -j 2 >/dev/null
(cd build/c-asan && ASAN_OPTIONS=halt_on_error=1:abort_on_error=1:detect_leaks=1 \
  UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 ctest --output-on-failure)
export RLBRIDGE_C_BUILD="$PWD/build/c" RLBRIDGE_TEST_REQUIRE_C=1
mkdir -p .test-logs
start=$SECONDS
suite=0
.venv/bin/python -m pytest "$@" 2>&1 | tee .test-logs/full-suite.log || suite=$?
echo "full suite: exit $suite, wall time $((SECONDS - start)) s"
matrix=0
bash scripts/test_matrix.sh || matrix=$?
# The closing line: every test of the run, the full suite's and the matrix's.
full=$(grep -E "[0-9]+ (passed|failed)|no tests ran" .test-logs/full-suite.log | tail -1 || true)
legs=$(cat .test-logs/matrix.summary 2>/dev/null || true)
count() { grep -oE "[0-9]+ $1" <<<"$2" | grep -oE "[0-9]+" || echo 0; }
passed=$(($(count passed "$full") + $(count passed "$legs")))
failed=$(($(count failed "$full") + $(count failed "$legs")))
skipped=$(($(count skipped "$full") + $(count skipped "$legs")))
[ "$suite" = 0 ] && [ "$matrix" = 0 ] || failed=$((failed > 0 ? failed : 1))
echo "all: $passed passed, $failed failed, $skipped skipped"
[ "$suite" = 0 ] && [ "$matrix" = 0 ]
