# Repairs the include directories that the PyPI `ros-jazzy-*` wheels hard-code.
#
# Each message package's exported `<pkg>::<pkg>__rosidl_generator_py` target lists the Python
# headers and numpy headers of the machine that built the wheel (/opt/python/cp311-cp311/...).
# CMake refuses to generate a build that links an imported target with a missing include
# directory, and rosidl_generator_py links every dependency's target. Rather than editing the
# installed wheel files (pip owns them; a reinstall or upgrade would undo the edit), we rewrite
# the property on the imported targets in this directory, after they are loaded: every listed
# directory that does not exist is replaced by this interpreter's Python and numpy include
# directories. Against an apt install all paths exist and nothing changes.

function(edgeloc_fix_wheel_include_dirs)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
  set(_replacement ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
  get_property(_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
  set(_fixed)
  foreach(_target IN LISTS _targets)
    if(NOT _target MATCHES "__rosidl_generator_py$")
      continue()
    endif()
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept)
    set(_missing FALSE)
    foreach(_dir IN LISTS _dirs)
      if(EXISTS "${_dir}")
        list(APPEND _kept "${_dir}")
      else()
        set(_missing TRUE)
      endif()
    endforeach()
    if(_missing)
      list(APPEND _kept ${_replacement})
      list(REMOVE_DUPLICATES _kept)
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
      list(APPEND _fixed ${_target})
    endif()
  endforeach()
  if(_fixed)
    list(LENGTH _fixed _count)
    message(STATUS "edgeloc: pointed ${_count} wheel-built Python targets at ${_replacement}")
  endif()
endfunction()
