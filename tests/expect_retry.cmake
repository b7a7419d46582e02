# A scene that blows up at cfl = 1 in frame 11: with --retries 0 the run fails (exit 1) naming
# the step and particle; by default the frame is retried with cfl halved and the run completes.
file(REMOVE_RECURSE ${OUT})
execute_process(COMMAND ${AMALGAM} run ${SCENE} --threads 1 --retries 0 --quiet --out ${OUT}/a
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 1 OR NOT err MATCHES "simulation failed: step [0-9]+ .*particle [0-9]+")
  message(FATAL_ERROR "expected a blow-up with --retries 0 (exit ${rc}):\n${out}${err}")
endif()
execute_process(COMMAND ${AMALGAM} run ${SCENE} --threads 1 --quiet --out ${OUT}/b
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 0 OR NOT err MATCHES "retrying frame [0-9]+ from its start with cfl = 0.5")
  message(FATAL_ERROR "expected a retried, completed run (exit ${rc}):\n${out}${err}")
endif()
file(STRINGS ${OUT}/b/diagnostics.csv rows)
list(LENGTH rows nrows)
if(NOT nrows EQUAL 13)
  message(FATAL_ERROR "expected 12 frames after the retry, diagnostics has ${nrows} lines")
endif()
