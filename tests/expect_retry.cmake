# A scene that trips the stability guard at its cfl: with --retries 0 the run fails (exit 1) naming
# the step and particle; by default the frame is retried from its start with cfl halved
# (RETRY_CFL) and the run completes with FRAMES frames. Used for MPM (tests/data/needs_retry.json)
# and peridynamics (tests/data/pd_needs_retry.json); tests/CMakeLists.txt says what trips each.
file(REMOVE_RECURSE ${OUT})
execute_process(COMMAND ${AMALGAM} run ${SCENE} --threads 1 --retries 0 --quiet --out ${OUT}/a
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 1 OR NOT err MATCHES "simulation failed: step [0-9]+ .*particle [0-9]+")
  message(FATAL_ERROR "expected a blow-up with --retries 0 (exit ${rc}):\n${out}${err}")
endif()
execute_process(COMMAND ${AMALGAM} run ${SCENE} --threads 1 --quiet --out ${OUT}/b
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 0 OR NOT err MATCHES "retrying frame [0-9]+ from its start with cfl = ${RETRY_CFL}")
  message(FATAL_ERROR "expected a retried, completed run (exit ${rc}):\n${out}${err}")
endif()
file(STRINGS ${OUT}/b/diagnostics.csv rows)
list(LENGTH rows nrows)
math(EXPR expected "${FRAMES} + 1")
if(NOT nrows EQUAL expected)
  message(FATAL_ERROR "expected ${FRAMES} frames after the retry, diagnostics has ${nrows} lines")
endif()
