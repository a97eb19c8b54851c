# Install rules and the Debian package (CPack): `cpack -G DEB` in the build folder (scripts/package.sh)
# writes oxbow_<version>_<arch>.deb. Files: cmake/packaging/ (server/README.md, "Debian package").
#
# Two components:
#   oxbow  /usr/bin/oxbow, its modules in /usr/lib/oxbow/ (MPI, the cluster's gRPC), its man pages (one per
#          command, from the binary's --help) and the README.
#          Also what `cmake --install build [--prefix P]` installs.
#   deb    what only makes sense in the package, installed at fixed absolute paths the maintainer scripts
#          and the unit name: oxbow.service, /etc/default/oxbow, the copyright file and changelog; and the
#          Python client (api/python) as a module of Debian's python3, in /usr/lib/python3/dist-packages
#          (a path only Debian's python3 reads). EXCLUDE_FROM_ALL, so `cmake --install` never writes to /etc
#          or /lib, nor a dist-packages folder no python3 reads (elsewhere: `pip install ./api/python`).
# The web page needs no file: server/http embeds it in the binary.

include(GNUInstallDirs)
set(_oxbow_pkg_src "${PROJECT_SOURCE_DIR}/cmake/packaging")
set(_oxbow_pkg_out "${PROJECT_BINARY_DIR}/packaging")
set(OXBOW_DEB_MAINTAINER "oxbow maintainers <maintainers@users.noreply.h-seed-76514774.example>"
    CACHE STRING "Maintainer field of the Debian package")

find_program(OXBOW_HELP2MAN help2man)
find_program(OXBOW_GZIP gzip REQUIRED)
# Debian's, the one the package's module is for; it runs the client's build backend (Python 3.11+).
find_program(OXBOW_PACKAGE_PYTHON3 python3 PATHS /usr/bin NO_DEFAULT_PATH)

# ---- component oxbow ----
# Full RELRO (bind now): the dynamic relocations are resolved at start, so the GOT is read-only while the
# server runs (lintian's hardening-no-bindnow); costs a few milliseconds at start.
target_link_options(oxbow PRIVATE LINKER:-z,now)
install(TARGETS oxbow RUNTIME DESTINATION "${CMAKE_INSTALL_BINDIR}" COMPONENT oxbow)
# The run-time modules (server/cli/modules/module_loader.h): the binary looks for them in
# <its folder>/../lib/oxbow, so the folder is lib/oxbow under the prefix, not the multiarch library folder.
install(TARGETS oxbow_mpi oxbow_cluster_module LIBRARY DESTINATION lib/oxbow COMPONENT oxbow)
# Generated at install time from the binary that is installed, so the pages always match it; costs the
# normal build nothing (about 2 s, for cpack or cmake --install only).
if(OXBOW_HELP2MAN)
  install(CODE "execute_process(COMMAND bash \"${_oxbow_pkg_src}/make-manpages.sh\" \"$<TARGET_FILE:oxbow>\"
                                        \"${PROJECT_VERSION}\" \"${_oxbow_pkg_out}/man\" COMMAND_ERROR_IS_FATAL ANY)"
          COMPONENT oxbow)
else()
  install(CODE "message(FATAL_ERROR \"help2man not found: it writes oxbow's man pages (scripts/install-deps.sh installs it)\")"
          COMPONENT oxbow)
endif()
install(DIRECTORY "${_oxbow_pkg_out}/man/" DESTINATION "${CMAKE_INSTALL_MANDIR}/man1" COMPONENT oxbow)
install(CODE "execute_process(COMMAND \"${OXBOW_GZIP}\" -9nc \"${PROJECT_SOURCE_DIR}/README.md\"
                              OUTPUT_FILE \"${_oxbow_pkg_out}/README.md.gz\" COMMAND_ERROR_IS_FATAL ANY)"
        COMPONENT oxbow)
install(FILES "${_oxbow_pkg_out}/README.md.gz" DESTINATION "${CMAKE_INSTALL_DOCDIR}" COMPONENT oxbow)

# ---- component deb ----
# A native package (no Debian revision): its changelog is changelog.gz.
string(TIMESTAMP OXBOW_DEB_DATE "%a, %d %b %Y %H:%M:%S +0000" UTC)  # honours SOURCE_DATE_EPOCH
set(OXBOW_DEB_VERSION "${PROJECT_VERSION}")
configure_file("${_oxbow_pkg_src}/changelog.in" "${_oxbow_pkg_out}/changelog" @ONLY)
install(CODE "execute_process(COMMAND \"${OXBOW_GZIP}\" -9nc \"${_oxbow_pkg_out}/changelog\"
                              OUTPUT_FILE \"${_oxbow_pkg_out}/changelog.gz\" COMMAND_ERROR_IS_FATAL ANY)
              execute_process(COMMAND bash \"${_oxbow_pkg_src}/make-default.sh\" \"$<TARGET_FILE:oxbow>\"
                                      \"${_oxbow_pkg_out}/default/oxbow\" COMMAND_ERROR_IS_FATAL ANY)"
        COMPONENT deb EXCLUDE_FROM_ALL)
install(FILES "${_oxbow_pkg_src}/copyright" "${_oxbow_pkg_out}/changelog.gz" DESTINATION "${CMAKE_INSTALL_DOCDIR}"
        COMPONENT deb EXCLUDE_FROM_ALL)
install(FILES "${_oxbow_pkg_src}/lintian-overrides" DESTINATION "${CMAKE_INSTALL_DATADIR}/lintian/overrides" RENAME oxbow
        COMPONENT deb EXCLUDE_FROM_ALL)
install(FILES "${_oxbow_pkg_src}/oxbow.service" DESTINATION /lib/systemd/system COMPONENT deb EXCLUDE_FROM_ALL)
install(FILES "${_oxbow_pkg_out}/default/oxbow" DESTINATION /etc/default PERMISSIONS OWNER_READ OWNER_WRITE
        COMPONENT deb EXCLUDE_FROM_ALL)
# The Python client: the folder oxbow_client/ and oxbow_client-VERSION.dist-info/ (METADATA; no RECORD, so
# pip leaves the files to dpkg), as the client's own build backend writes them (api/python/README.md).
# Without bytecode: postinst compiles it with py3compile and prerm removes it with py3clean, as dh_python3's
# snippets do.
if(OXBOW_PACKAGE_PYTHON3)
  install(CODE "execute_process(COMMAND \"${OXBOW_PACKAGE_PYTHON3}\" -B \"${PROJECT_SOURCE_DIR}/api/python/_build/oxbow_build.py\"
                                        install \"${_oxbow_pkg_out}/python\" --installer dpkg COMMAND_ERROR_IS_FATAL ANY)"
          COMPONENT deb EXCLUDE_FROM_ALL)
else()
  install(CODE "message(FATAL_ERROR \"/usr/bin/python3 not found: it writes the package's Python client (scripts/install-deps.sh installs it)\")"
          COMPONENT deb EXCLUDE_FROM_ALL)
endif()
install(DIRECTORY "${_oxbow_pkg_out}/python/" DESTINATION lib/python3/dist-packages COMPONENT deb EXCLUDE_FROM_ALL)

# ---- CPack ----
set(CPACK_GENERATOR DEB)
set(CPACK_SOURCE_GENERATOR "")
set(CPACK_PACKAGE_NAME oxbow)
set(CPACK_PACKAGE_VERSION "${PROJECT_VERSION}")
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_STRIP_FILES ON)
# Both components in one package.
set(CPACK_COMPONENTS_ALL oxbow deb)
set(CPACK_DEB_COMPONENT_INSTALL ON)
set(CPACK_COMPONENTS_GROUPING ALL_COMPONENTS_IN_ONE)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_MAINTAINER "${OXBOW_DEB_MAINTAINER}")
set(CPACK_DEBIAN_PACKAGE_SECTION graphics)
set(CPACK_DEBIAN_PACKAGE_PRIORITY optional)
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "instance-level image retrieval server")
string(CONCAT CPACK_PACKAGE_DESCRIPTION  # CPack indents the lines for the control file
    "oxbow finds the photos of a collection that show the same object or place as\n"
    "a query photo (a crop, another viewpoint, scale, rotation or lighting) and the\n"
    "region that matched: SIFT/RootSIFT features, a visual-word TF-IDF index,\n"
    "spatial re-ranking and query expansion. It runs as an HTTP JSON server with a\n"
    "search page (oxbow.service) and as a command line tool. The Python client of\n"
    "its HTTP API is the python3 module oxbow_client.")
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)     # dpkg-shlibdeps fills Depends from the linked libraries
# adduser: postinst creates the system user. OpenCV's image codecs are loaded at run time, not linked
# (sift/opencv_codecs.h), so dpkg-shlibdeps cannot see them.
set(CPACK_DEBIAN_PACKAGE_DEPENDS "adduser, libopencv-imgcodecs406")
# The Python client's module needs python3; the server does not.
set(CPACK_DEBIAN_PACKAGE_SUGGESTS "python3")
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    "${_oxbow_pkg_src}/postinst" "${_oxbow_pkg_src}/prerm" "${_oxbow_pkg_src}/postrm" "${_oxbow_pkg_src}/conffiles")
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
include(CPack)
