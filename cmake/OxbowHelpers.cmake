# Helpers shared by the module CMakeLists.
#
# oxbow_add_module(NAME <target> [PUBLIC_DEPS ...] [PRIVATE_DEPS ...] [SUBDIRS ...])
#   One static library per module folder, from every *.cc in the folder and in its SUBDIRS except *_test.cc
#   and *_main.cc. Include paths are rooted at the repository, so code writes
#   #include "sift/types.h".
#   Every *_test.cc in the folder becomes its own GoogleTest executable and ctest entry, linked
#   against the module (oxbow_add_gtest). The benchmark programs are in eval/bench/.
#
# oxbow_add_gtest(NAME <target> SOURCE <file> [LABELS ...])
#   Registers the GoogleTest executable <target> (built from <file>) with ctest and links it with
#   tests/gtest_main.cc instead of GTest::gtest_main: a binary whose tests all skipped exits with
#   OXBOW_GTEST_SKIP_CODE, which ctest reports as skipped, not passed. Test suites whose name contains
#   "SharedData" (their tests need ../shared/data or $OXBOW_SHARED_DATA, tests/support/shared_data.h) run as a second
#   ctest entry <target>_shared_data, so that ctest shows them skipped when the data is absent.

set(OXBOW_COMPILE_WARNINGS -Wall -Wextra -Wpedantic -Wshadow -Wnon-virtual-dtor -Wno-unused-parameter)

function(oxbow_target_defaults target)
  target_compile_options(${target} PRIVATE ${OXBOW_COMPILE_WARNINGS})
  if(OXBOW_WERROR)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
  if(OXBOW_MARCH)
    target_compile_options(${target} PRIVATE -march=${OXBOW_MARCH})
  endif()
  if(OXBOW_SANITIZE)
    string(REPLACE ";" "," _san "${OXBOW_SANITIZE}")
    target_compile_options(${target} PRIVATE -fsanitize=${_san} -fno-omit-frame-pointer -fno-sanitize-recover=all)
    target_link_options(${target} PRIVATE -fsanitize=${_san})
  endif()
  if(OXBOW_FUZZ)  # coverage instrumentation + libFuzzer runtime (cmake/OxbowFuzz.cmake)
    target_link_libraries(${target} PRIVATE oxbow_fuzz_runtime)
  endif()
endfunction()

set(OXBOW_GTEST_SKIP_CODE 77)  # kAllSkipped in tests/gtest_main.cc

function(oxbow_add_gtest)
  cmake_parse_arguments(G "" "NAME;SOURCE" "LABELS" ${ARGN})
  if(NOT TARGET oxbow_gtest_main)
    add_library(oxbow_gtest_main STATIC ${PROJECT_SOURCE_DIR}/tests/gtest_main.cc)
    target_link_libraries(oxbow_gtest_main PUBLIC GTest::gtest)
    oxbow_target_defaults(oxbow_gtest_main)
    if(OXBOW_SANITIZE MATCHES "undefined")
      set_source_files_properties(${PROJECT_SOURCE_DIR}/tests/gtest_main.cc PROPERTIES COMPILE_OPTIONS -O0)
    endif()
  endif()
  target_link_libraries(${G_NAME} PRIVATE oxbow_gtest_main GTest::gtest)
  if(OXBOW_SANITIZE MATCHES "undefined")
    # The test's own source at -O0 in UBSan builds: GCC's UBSan instrumentation at -O1 doubles the
    # compile time of a GoogleTest file (batch_add_test.cc: 46 s at -O1, 20 s at -O0), and the code
    # under test (the modules, and any module source a test compiles in) keeps the build's -O1.
    set_source_files_properties(${G_SOURCE} PROPERTIES COMPILE_OPTIONS -O0)
  elseif(CMAKE_BUILD_TYPE STREQUAL "Release" AND NOT OXBOW_SANITIZE)
    # The test's own source at -O1 in a release build: -O3 spends its time optimising GoogleTest's
    # macros (collections_test.cc: 28 s at -O3, 22 s at -O1; cluster_test.cc: 43 s, 31 s), while the
    # code under test, in the modules, keeps -O3.
    set_source_files_properties(${G_SOURCE} PROPERTIES COMPILE_OPTIONS -O1)
  endif()
  file(STRINGS ${G_SOURCE} _shared_data_tests REGEX "^TEST(_F|_P)?\\([A-Za-z0-9_]*SharedData")
  if(_shared_data_tests)
    add_test(NAME ${G_NAME} COMMAND ${G_NAME} --gtest_filter=-*SharedData* WORKING_DIRECTORY ${PROJECT_SOURCE_DIR})
    add_test(NAME ${G_NAME}_shared_data COMMAND ${G_NAME} --gtest_filter=*SharedData*
      WORKING_DIRECTORY ${PROJECT_SOURCE_DIR})
    set(_entries ${G_NAME} ${G_NAME}_shared_data)
  else()
    add_test(NAME ${G_NAME} COMMAND ${G_NAME} WORKING_DIRECTORY ${PROJECT_SOURCE_DIR})
    set(_entries ${G_NAME})
  endif()
  set_tests_properties(${_entries} PROPERTIES SKIP_RETURN_CODE ${OXBOW_GTEST_SKIP_CODE})
  if(G_LABELS)
    set_tests_properties(${_entries} PROPERTIES LABELS "${G_LABELS}")
  endif()
endfunction()

function(oxbow_add_module)
  cmake_parse_arguments(M "" "NAME" "PUBLIC_DEPS;PRIVATE_DEPS;TEST_DEPS;SUBDIRS" ${ARGN})
  # The module's sources: the folder's *.cc and those of its SUBDIRS (rooms of the module, e.g. index/search).
  set(_globs "${CMAKE_CURRENT_SOURCE_DIR}/*.cc")
  foreach(d IN LISTS M_SUBDIRS)
    list(APPEND _globs "${CMAKE_CURRENT_SOURCE_DIR}/${d}/*.cc")
  endforeach()
  file(GLOB _all CONFIGURE_DEPENDS ${_globs})
  set(_srcs "")
  set(_tests "")
  foreach(f IN LISTS _all)
    if(f MATCHES "_test\\.cc$")
      list(APPEND _tests ${f})
    elseif(NOT f MATCHES "_main\\.cc$")
      list(APPEND _srcs ${f})
    endif()
  endforeach()
  if(_srcs)
    add_library(${M_NAME} STATIC ${_srcs})
    target_include_directories(${M_NAME} PUBLIC ${PROJECT_SOURCE_DIR})
    target_link_libraries(${M_NAME} PUBLIC ${M_PUBLIC_DEPS} Threads::Threads PRIVATE ${M_PRIVATE_DEPS})
    target_compile_definitions(${M_NAME} PUBLIC OXBOW_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
    oxbow_target_defaults(${M_NAME})
  else()  # a module with headers only (so far)
    add_library(${M_NAME} INTERFACE)
    target_include_directories(${M_NAME} INTERFACE ${PROJECT_SOURCE_DIR})
    target_link_libraries(${M_NAME} INTERFACE ${M_PUBLIC_DEPS} Threads::Threads)
  endif()

  if(OXBOW_BUILD_TESTS)
    foreach(t IN LISTS _tests)
      get_filename_component(_n ${t} NAME_WE)
      add_executable(${_n} ${t})
      target_link_libraries(${_n} PRIVATE ${M_NAME} ${M_PRIVATE_DEPS} ${M_TEST_DEPS})
      oxbow_target_defaults(${_n})
      oxbow_add_gtest(NAME ${_n} SOURCE ${t} LABELS ${M_NAME})
    endforeach()
  endif()
endfunction()
