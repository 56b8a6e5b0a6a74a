#!/usr/bin/env bash
# The test command (README): install what the tests need, lint, type-check, run the tests
# (the full suite, on python3: 3.11 here), then the Python x ROS 2 matrix (scripts/test_matrix.sh:
# the SDK, server, wire, CLI and ROS 2 tests on Python 3.10, 3.12 and 3.13, ROS 2 Jazzy's wheels
# and a graph across releases, the README's examples after a plain `pip install .` on each
# Python). Works on a fresh machine with only Python 3.11, pip and apt: a Python that is not
# there is a loud MISSING line and its legs are skipped, except with CI=true, where it fails.
# Extra args go to the full suite's pytest. `bash scripts/test.sh --quick`: the fast lane below.
set -euo pipefail
cd "$(dirname "$0")/.."

# --quick: the edit-test loop (README, "Run the tests"). No apt, no ROS, no matrix, no mypy:
# lint, then the tests a change most often breaks (the codec, rings and channels, a live
# server over loopback, the CLI's basics), without the slow kinds (markers in pyproject.toml),
# in under two minutes on a 2-core machine. Uses .venv as it is; makes it (pure Python, no ROS
# extras) only if it is missing. Extra args go to pytest. The full run below is what CI runs.
if [ "${1:-}" = "--quick" ]; then
  shift
  if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
    RLBRIDGE_PURE_PYTHON=1 .venv/bin/python -m pip install -q -e ".[test]"
  fi
  quick=(
    tests/architecture tests/wire
    tests/csp/test_ring.py tests/csp/test_ring_stamped.py tests/csp/test_channel.py
    tests/csp/test_doorbell.py
    tests/client/test_send_round.py tests/client/test_policies.py tests/client/test_pacing.py
    tests/server/test_server_udp.py tests/server/test_server_tcp.py
    tests/server/test_server_routing.py tests/server/test_bundles.py
    tests/server/test_value_path_parity.py tests/server/test_udp_sink.py
    tests/server/test_admission.py tests/server/test_flow_credit.py tests/server/test_stats.py
    tests/server/test_policies_server.py tests/server/test_lifetime.py
    tests/client/test_client_bridge.py tests/client/test_receiver_parity.py
    tests/client/test_incoming_deliver.py tests/client/test_receive_datagrams.py
    tests/client/test_send_thread.py tests/client/test_send_inline.py
    tests/csp/test_idle.py
    tests/security/test_bad_input.py tests/packaging/test_compiled_edited.py
    tests/cli/test_options.py tests/cli/test_messages.py tests/cli/test_exit_codes.py
  )
  .venv/bin/ruff check src tests scripts benchmarks examples setup.py
  start=$SECONDS
  rc=0
  .venv/bin/python -m pytest -q -p no:cacheprovider -m "not slow and not ros2 and not netem" \
    "${quick[@]}" "$@" || rc=$?
  echo "quick lane: exit $rc, wall time $((SECONDS - start)) s (the full run: bash scripts/test.sh)"
  exit "$rc"
fi

# System packages: the network-emulator and stress tests' tools, libsodium for the cipher
# setup.py builds, and the C client's (clients/c) build tools and libraries. Without root they
# are skipped, and the tests that need them skip with the reason printed.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  need=()
  command -v ip >/dev/null 2>&1 || need+=(iproute2)
  command -v nft >/dev/null 2>&1 || need+=(nftables)
  command -v stress >/dev/null 2>&1 || need+=(stress)
  command -v cmake >/dev/null 2>&1 || need+=(cmake)
  command -v cc >/dev/null 2>&1 || need+=(gcc)
  [ -e /usr/include/sodium.h ] || need+=(libsodium-dev)
  [ -e /usr/include/msgpack.h ] || need+=(libmsgpack-dev)
  [ -e /usr/include/cmocka.h ] || need+=(libcmocka-dev)
  [ -e /usr/include/openssl/ssl.h ] || need+=(libssl-dev)  # the C client's TLS sessions
  if [ "${#need[@]}" -gt 0 ]; then
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
  fi
fi

python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test,ros2,compare]"

# The compiled value path must not depend on libsodium (setup.py: each extension optional on
# its own). Install a copy of the package once more, editable as the README's quick start does,
# in a venv of its own and a mount namespace where libsodium's headers are hidden; it must
# report the value path compiled and sealing by cryptography's cipher. Needs root (unshare).
nosodium=$(mktemp -d)
if [ "$(id -u)" = 0 ] && unshare --mount true 2>/dev/null; then
  tar -c --exclude='*.so' --exclude=__pycache__ --exclude=_compiled_sources.json \
    setup.py pyproject.toml README.md LICENSE src | tar -x -C "$nosodium"
  mkdir "$nosodium/empty"
  python3 -m venv "$nosodium/venv"
  unshare --mount bash -ec '
    [ ! -e /usr/include/sodium ] || mount --bind "$1/empty" /usr/include/sodium
    [ ! -e /usr/include/sodium.h ] || mount --bind /dev/null /usr/include/sodium.h
    "$1/venv/bin/python" -m pip install -q -e "$1" >"$1/pip.log" 2>&1 || { cat "$1/pip.log"; exit 1; }
    "$1/venv/bin/rlbridge" --version' _ "$nosodium" | tee "$nosodium/version"
  grep -q "^value path: compiled" "$nosodium/version" && grep -q "^sealing.*: cryptography" \
    "$nosodium/version" || { echo "FAILED: without libsodium's headers the value path is not compiled"; exit 1; }
  echo "install without libsodium's headers: value path compiled"
elif [ "${CI:-}" = true ]; then
  echo "MISSING: root and a mount namespace (unshare --mount) for the install without libsodium's headers"; exit 1
else
  echo "MISSING: root and a mount namespace (unshare --mount): the install without libsodium's headers is not checked"
fi
rm -rf "$nosodium"

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
mkdir -p .test-logs
{ cmake -S clients/c -B build/c -DRLB_WERROR=ON && cmake --build build/c -j 2; } \
  >.test-logs/c-build.log 2>&1 || { cat .test-logs/c-build.log; echo "FAILED: the C client does not build"; exit 1; }
(cd build/c && ctest --output-on-failure)
# clang (the install step above leaves it out: it is large) warns where gcc does not; where it is,
# the same build and unit tests once more with it, into build/c-clang (no sanitizer build).
if command -v clang >/dev/null 2>&1; then
  { CC=clang cmake -S clients/c -B build/c-clang -DRLB_WERROR=ON && cmake --build build/c-clang -j 2; } \
    >.test-logs/c-clang-build.log 2>&1 || { cat .test-logs/c-clang-build.log; echo "FAILED: the C client does not build with clang"; exit 1; }
  (cd build/c-clang && ctest --output-on-failure)
else
  echo "clang not installed: the C client's clang build is skipped (gcc's ran)"
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
