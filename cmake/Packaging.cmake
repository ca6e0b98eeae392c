# CPack: `cpack --config build/CPackConfig.cmake -G DEB` (or `cmake --build build --target
# package`) turns the install rules of deploy/CMakeLists.txt into magcal_<version>_<arch>.deb.
# Maintainer scripts and conffiles: deploy/debian/. Runtime dependencies come from
# dpkg-shlibdeps (dpkg-dev) plus what the maintainer scripts call.
set(CPACK_GENERATOR "DEB")
set(CPACK_PACKAGE_NAME "magcal")
set(CPACK_PACKAGE_VERSION "${PROJECT_VERSION}")
set(CPACK_PACKAGE_VENDOR "magcal")
set(CPACK_PACKAGE_CONTACT "magcal maintainers <magcal@localhost>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY
    "ground-station magnetometer calibration daemon (magcald) and CLI (magcal)")
set(CPACK_PACKAGE_DESCRIPTION
    "magcald ingests spacecraft magnetometer telemetry from LCM, keeps it in SQLite, tracks \
every spacecraft with an unscented Kalman filter, runs scheduled batch refits (centered \
solution + Levenberg-Marquardt + alignment), gates every result and publishes it. magcal is \
the command line: simulate, fit, refit, history, status. Ships a hardened systemd unit \
(Type=notify, watchdog) and Prometheus alert rules.")
# Absolute /etc paths for the config (deploy/install_unit_and_config.cmake): install with
# DESTDIR into the staging tree, prefix /usr.
set(CPACK_SET_DESTDIR ON)
set(CPACK_INSTALL_PREFIX "/usr")
set(CPACK_PACKAGING_INSTALL_PREFIX "/usr")
set(CPACK_STRIP_FILES ON)

set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)  # magcal_<version>_<arch>.deb
set(CPACK_DEBIAN_PACKAGE_SECTION "science")
set(CPACK_DEBIAN_PACKAGE_PRIORITY "optional")
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
# postinst: adduser; postinst/postrm: deb-systemd-helper, deb-systemd-invoke.
set(CPACK_DEBIAN_PACKAGE_DEPENDS "adduser, init-system-helpers (>= 1.54~)")
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    "${PROJECT_SOURCE_DIR}/deploy/debian/postinst;${PROJECT_SOURCE_DIR}/deploy/debian/prerm;${PROJECT_SOURCE_DIR}/deploy/debian/postrm;${PROJECT_SOURCE_DIR}/deploy/debian/conffiles")
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)

include(CPack)
