# Runs amalgam with ARGS (a ;-list) and passes if it exits with EXPECT_RC and prints EXPECT_REGEX.
execute_process(COMMAND ${AMALGAM} ${ARGS} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL ${EXPECT_RC})
  message(FATAL_ERROR "expected exit ${EXPECT_RC}, got ${rc}\n${out}${err}")
endif()
if(NOT "${out}${err}" MATCHES "${EXPECT_REGEX}")
  message(FATAL_ERROR "message does not match '${EXPECT_REGEX}':\n${out}${err}")
endif()
message(STATUS "exit ${rc}: ${err}")
