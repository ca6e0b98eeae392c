# LCM 1.3.1 on Debian ships no CMake config (and its pkg-config file needs glib-dev):
# build an imported target from the header, the library and lcm-gen.
find_path(LCM_INCLUDE_DIR lcm/lcm-cpp.hpp REQUIRED)
find_library(LCM_LIBRARY lcm REQUIRED)
find_program(LCM_GEN_EXECUTABLE lcm-gen REQUIRED)
if(NOT TARGET lcm::lcm)
  add_library(lcm::lcm UNKNOWN IMPORTED)
  set_target_properties(lcm::lcm PROPERTIES
    IMPORTED_LOCATION "${LCM_LIBRARY}"
    INTERFACE_INCLUDE_DIRECTORIES "${LCM_INCLUDE_DIR}")
endif()
