#!/usr/bin/env bash
# The Python x ROS 2 matrix (docs/ros2.md, "What is tested"), run by scripts/test.sh after the
# full suite; runs alone too: `bash scripts/test_matrix.sh` (it needs .venv from test.sh for
# the cross-release leg). Legs, each in a venv of its own, RLBRIDGE_MATRIX_JOBS (2) at a time:
#
#   py3.10, py3.12, py3.13  the SDK, server, wire, CLI, CSP, interop, docs and ROS 2 adapter
#                           tests on that Python, with the current ROS wheels (.venv-X.Y)
#   jazzy                   the ROS 2 adapter tests on Jazzy's rclpy 7.1 wheels and Python 3.12
#                           (.venv-jazzy), and the cross-release graph: server on one release,
#                           ROS node on the other, both ways (tests/adapters/test_ros2_cross_release.py)
#   readme-3.10 .. 3.13     a fresh venv, `pip install .` as a user does (compiling the value
#                           path with mypyc: setup.py), the README's examples against
#                           `rlbridge serve` (scripts/readme_example.py); 3.11 without compiling
#
# The py and jazzy legs and readme-3.11 install and test with RLBRIDGE_PURE_PYTHON=1: the
# Python files, as on a machine without a compiler (scripts/test.sh's full suite tests the
# compiled modules on 3.11, the other readme legs run them on 3.10, 3.12 and 3.13); a compile
# costs ~45 s of CPU (docs/benchmarks.md, "Compiled value path").
#
# Interpreters come from pyenv ($PYENV_ROOT or ~/.pyenv) or `pythonX.Y` on PATH. A missing one
# is a loud "MISSING" line and its legs are skipped; with CI=true it fails the run. A leg fails
# on any test failure, and on pytest's exit 5 (no test ran). The last line sums all legs.
set -euo pipefail
cd "$(dirname "$0")/.."

LOGS=.test-logs
MAIN_VERSION=$(python3 -c 'import sys; print("%d.%d" % sys.version_info[:2])')
VERSIONS=(3.10 3.11 3.12 3.13)
JAZZY_PYTHON=3.12  # Ubuntu 24.04's, the Python Jazzy is built for
SUBSET=(tests/wire tests/server tests/client tests/cli tests/csp tests/hrt tests/interop tests/docs
        tests/adapters)

# A python executable of version $1 (X.Y), or nothing.
find_python() {
  local version=$1 candidate root="${PYENV_ROOT:-$HOME/.pyenv}"
  local candidates=()
  if [ -d "$root/versions" ]; then
    while IFS= read -r candidate; do candidates+=("$candidate"); done < <(
      ls -d "$root/versions/$version".*/bin/python 2>/dev/null | sort -V -r)
  fi
  candidate=$(command -v "python$version" 2>/dev/null || true)
  [ -n "$candidate" ] && candidates+=("$candidate")
  for candidate in "${candidates[@]}"; do
    if [ -x "$candidate" ] && "$candidate" -c "import sys, venv, ensurepip
sys.exit(sys.version_info[:2] != tuple(map(int, '$version'.split('.'))))" 2>/dev/null; then
      echo "$candidate"
      return
    fi
  done
}

# A venv $1 on python $2 with `pip install $3...` in it (kept between runs: pip's cache is warm).
make_venv() {
  local venv=$1 python=$2
  shift 2
  "$python" -m venv "$venv"
  "$venv/bin/python" -m pip install -q --upgrade pip
  "$venv/bin/python" -m pip install -q "$@"
}

# -- one leg: run in a process of its own (`bash test_matrix.sh --leg KIND ARG...`) -----------
if [ "${1:-}" = "--leg" ]; then
  kind=$2 version=$3 python=$4
  export RLBRIDGE_TEST_REQUIRE_ROS2=1  # an rclpy that does not import fails, never skips
  case $kind in
    py)
      export RLBRIDGE_PURE_PYTHON=1  # the tests on the Python files (see the header)
      unset RLBRIDGE_TEST_REQUIRE_COMPILED
      make_venv ".venv-$version" "$python" -e ".[test,ros2]"
      exec ".venv-$version/bin/python" -m pytest -q -p no:randomly "${SUBSET[@]}" ;;
    jazzy)
      export RLBRIDGE_PURE_PYTHON=1
      unset RLBRIDGE_TEST_REQUIRE_COMPILED
      make_venv .venv-jazzy "$python" -e ".[test,ros2-jazzy]"
      [ -x .venv/bin/python ] || { echo "no .venv (the current wheels): run scripts/test.sh"; exit 1; }
      RLBRIDGE_ROS_OTHER_PYTHON="$PWD/.venv/bin/python" \
        exec .venv-jazzy/bin/python -m pytest -q -p no:randomly tests/adapters ;;
    readme)
      # 3.11: the pure install a machine without a compiler gets (the full suite tests the
      # compiled modules on 3.11); the other Pythons compile, as a user's `pip install .` does.
      if [ "$version" = 3.11 ]; then export RLBRIDGE_PURE_PYTHON=1; unset RLBRIDGE_TEST_REQUIRE_COMPILED; fi
      rm -rf ".venv-user-$version"
      make_venv ".venv-user-$version" "$python" .
      exec ".venv-user-$version/bin/python" scripts/readme_example.py ;;
  esac
  exit 2
fi

# -- the pool ---------------------------------------------------------------------------------
mkdir -p "$LOGS"
rm -f "$LOGS"/*.rc "$LOGS"/py*.log "$LOGS"/jazzy.log "$LOGS"/readme-*.log "$LOGS/matrix.summary"
declare -A python_of
missing=()
for version in "${VERSIONS[@]}"; do
  python_of[$version]=$(find_python "$version")
  if [ -z "${python_of[$version]}" ]; then
    missing+=("$version")
    echo "MISSING: no Python $version (pyenv or python$version on PATH): its legs are SKIPPED" >&2
  fi
done
if [ "${#missing[@]}" -gt 0 ] && [ "${CI:-}" = true ]; then
  echo "matrix: CI=true and Python ${missing[*]} missing: failing" >&2
  exit 1
fi

legs=()  # "name kind version"
for version in "${VERSIONS[@]}"; do
  [ -n "${python_of[$version]}" ] && [ "$version" != "$MAIN_VERSION" ] && legs+=("py$version py $version")
done
[ -n "${python_of[$JAZZY_PYTHON]}" ] && legs+=("jazzy jazzy $JAZZY_PYTHON")
for version in "${VERSIONS[@]}"; do
  [ -n "${python_of[$version]}" ] && legs+=("readme-$version readme $version")
done

jobs_max=${RLBRIDGE_MATRIX_JOBS:-2}
# ROS 2 legs running at once get distinct domain ids: base, base+1, ... (at most 8 legs).
domain=${RLBRIDGE_TEST_ROS_DOMAIN_BASE:-$((1 + $$ % 90))}
start=$SECONDS
echo "matrix: ${#legs[@]} legs, $jobs_max at a time, logs in $LOGS/"
for leg in "${legs[@]}"; do
  read -r name kind version <<<"$leg"
  while [ "$(jobs -rp | wc -l)" -ge "$jobs_max" ]; do wait -n || true; done
  {
    set +e
    t0=$SECONDS
    RLBRIDGE_TEST_ROS_DOMAIN_ID=$domain bash "$0" --leg "$kind" "$version" \
      "${python_of[$version]}" >"$LOGS/$name.log" 2>&1 </dev/null
    echo "$? $((SECONDS - t0))" >"$LOGS/$name.rc"
  } &
  domain=$((domain + 1))
done
wait

failed=0 passed=0 failures=0 skipped=0
for leg in "${legs[@]}"; do
  read -r name kind version <<<"$leg"
  read -r rc seconds <"$LOGS/$name.rc"
  if [ "$kind" = readme ]; then
    last=$(grep -h "^readme_example:" "$LOGS/$name.log" | tail -1)
    [ "$rc" = 0 ] && passed=$((passed + 1)) || failures=$((failures + 1))
  else
    last=$(grep -hE "^(=+ )?[0-9]+ (passed|failed|error)|no tests ran" "$LOGS/$name.log" | tail -1)
    for word in passed failed skipped error errors; do
      n=$(grep -oE "[0-9]+ $word" <<<"$last" | grep -oE "[0-9]+" || true)
      case $word in
        passed) passed=$((passed + ${n:-0})) ;;
        skipped) skipped=$((skipped + ${n:-0})) ;;
        *) failures=$((failures + ${n:-0})) ;;
      esac
    done
    [ "$rc" = 5 ] && last="pytest ran no test (exit 5): $last"
  fi
  printf '%-12s %-4s %4ss  %s\n' "$name" "$([ "$rc" = 0 ] && echo ok || echo FAIL)" "$seconds" "$last"
  if [ "$rc" != 0 ]; then
    failed=1
    echo "---- last lines of $LOGS/$name.log ----"
    tail -n 60 "$LOGS/$name.log"
    echo "----"
  fi
done
echo "matrix: wall time $((SECONDS - start)) s; skipped legs: ${missing[*]:-none}"
[ "$failed" = 0 ] || failures=$((failures > 0 ? failures : 1))
echo "matrix: $passed passed, $failures failed, $skipped skipped" | tee "$LOGS/matrix.summary"
exit "$failed"
