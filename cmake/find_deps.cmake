# Dependency lookups shared by the main project (CMakeLists.txt) and the fuzz project
# (fuzz/CMakeLists.txt), so both find the same libraries the same way.

# simu_find_yaml_cpp(<var>): finds yaml-cpp and sets <var> to its target name (yaml-cpp::yaml-cpp in
# 0.8, yaml-cpp in 0.7 as on Debian 12).
macro(simu_find_yaml_cpp var)
  find_package(yaml-cpp REQUIRED)
  if(TARGET yaml-cpp::yaml-cpp)
    set(${var} yaml-cpp::yaml-cpp)
  else()
    set(${var} yaml-cpp)
  endif()
endmacro()

# simu_find_opencv(): OpenCV's core, imgproc and imgcodecs; sets OpenCV_INCLUDE_DIRS and OpenCV_LIBS.
# Debian's per-module -dev packages ship no OpenCVConfig.cmake: the modules are found directly.
macro(simu_find_opencv)
  find_path(OpenCV_INCLUDE_DIRS opencv2/core.hpp PATH_SUFFIXES opencv4 REQUIRED)
  set(OpenCV_LIBS)
  foreach(m core imgproc imgcodecs)
    find_library(OpenCV_${m}_LIB opencv_${m} REQUIRED)
    list(APPEND OpenCV_LIBS ${OpenCV_${m}_LIB})
  endforeach()
endmacro()
