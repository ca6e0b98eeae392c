# Install-time part of deploy/CMakeLists.txt: the systemd unit with its paths set to the
# install prefix, and the example config as the live config unless one exists.
# deploy/magcald.service is written for prefix /usr (the .deb); other prefixes get it rewritten.
set(prefix "${CMAKE_INSTALL_PREFIX}")
if(prefix STREQUAL "/usr")
  set(sysconf "/etc")  # FHS, as GNUInstallDirs does for /usr
  # The state directory, listed in the package (postinst gives it to the magcal user; dpkg
  # never removes it while the database is in it). Elsewhere StateDirectory= creates it.
  file(MAKE_DIRECTORY "$ENV{DESTDIR}/var/lib/magcal")
  file(CHMOD "$ENV{DESTDIR}/var/lib/magcal" DIRECTORY_PERMISSIONS
       OWNER_READ OWNER_WRITE OWNER_EXECUTE GROUP_READ GROUP_EXECUTE)
else()
  set(sysconf "${prefix}/etc")
endif()

file(READ "${MAGCAL_DEPLOY_SOURCE_DIR}/magcald.service" unit)
string(REPLACE "/usr/bin/magcald" "${prefix}/bin/magcald" unit "${unit}")
string(REPLACE "/etc/magcal/" "${sysconf}/magcal/" unit "${unit}")
string(REPLACE "/usr/share/doc/magcal/" "${prefix}/share/doc/magcal/" unit "${unit}")
set(staged "${CMAKE_CURRENT_BINARY_DIR}/magcald.service.install")
file(WRITE "${staged}" "${unit}")
file(INSTALL "${staged}" DESTINATION "${prefix}/lib/systemd/system"
     RENAME magcald.service PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
file(REMOVE "${staged}")

# A config edited by the operator survives a re-install (dpkg: a conffile, deploy/debian).
if(EXISTS "$ENV{DESTDIR}${sysconf}/magcal/magcald.toml")
  message(STATUS "Keeping: $ENV{DESTDIR}${sysconf}/magcal/magcald.toml")
else()
  file(INSTALL "${MAGCAL_DEPLOY_SOURCE_DIR}/magcald.example.toml"
       DESTINATION "${sysconf}/magcal" RENAME magcald.toml
       PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
endif()
