# The proofs of issue 28's points 6 and 7 and the C client's benchmark program, included at the
# end of clients/c/CMakeLists.txt (the library, its warnings, rlb_progs and the test switch exist
# by now).
#
#  - rt_seccomp: the loop thread under a seccomp filter (tests/c_client/test_c_realtime.py).
#  - fuzz_decode: the fuzz corpus and random bytes through the receive path (ctest).
#  - rlb_rt_bench: benchmarks/c_client_rt.py's loop, jitter and latency program.
#
# -DRLB_SANITIZE=ON (CMakeLists.txt) builds these under ASan and UBSan too; scripts/test.sh runs
# fuzz_decode so in build/c-asan.

set(RLB_PROOF_DIR ${CMAKE_CURRENT_LIST_DIR})
set(RLB_REPO_ROOT ${CMAKE_CURRENT_LIST_DIR}/../../..)

function(rlb_proof_program name)
  add_executable(${name} ${ARGN})
  target_compile_options(${name} PRIVATE ${RLB_WARNINGS})
  target_compile_definitions(${name} PRIVATE _POSIX_C_SOURCE=200809L _DEFAULT_SOURCE)
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR})
endfunction()

if(CMAKE_SYSTEM_NAME STREQUAL "Linux")
  rlb_proof_program(rt_seccomp ${RLB_PROOF_DIR}/rt_seccomp.c)
  target_link_libraries(rt_seccomp PRIVATE rlbridge rlb_progs)
endif()

rlb_proof_program(rlb_rt_bench ${RLB_REPO_ROOT}/benchmarks/c_client/rlb_rt_bench.c)
target_link_libraries(rlb_rt_bench PRIVATE rlbridge rlb_progs)

# The receive path through the library's internal functions (src/conn.h): the static
# library only (a shared one exports rlb_* alone).
if(NOT BUILD_SHARED_LIBS)
  rlb_proof_program(fuzz_decode ${RLB_PROOF_DIR}/fuzz_decode.c)
  target_include_directories(fuzz_decode PRIVATE src)
  target_link_libraries(fuzz_decode PRIVATE rlbridge)
endif()

if(RLB_TESTS AND TARGET fuzz_decode)
  enable_testing()
  set(RLB_FUZZ_RANDOM 2000 CACHE STRING "fuzz_decode: generated inputs after the corpus")
  add_test(NAME fuzz_decode COMMAND fuzz_decode --random ${RLB_FUZZ_RANDOM}
    ${RLB_REPO_ROOT}/fuzz/corpus/decoder ${RLB_REPO_ROOT}/fuzz/corpus/server)
  if(RLB_SANITIZE)
    set_tests_properties(fuzz_decode PROPERTIES ENVIRONMENT
      "ASAN_OPTIONS=halt_on_error=1:detect_leaks=1:abort_on_error=1;UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1")
  endif()
endif()
