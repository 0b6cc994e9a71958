# The CMake of every interface package in ros/ (packages without a PyPI wheel), built into .venv
# by scripts/build_ros_msgs.sh against the rosidl generators from PyPI.
# Use: project(NAME), include() this file, vmocap_interfaces(MSGS msg/A.msg ... DEPENDENCIES pkg ...).
macro(vmocap_interfaces)
  cmake_parse_arguments(VMI "" "" "MSGS;DEPENDENCIES" ${ARGN})
  find_package(ament_cmake REQUIRED)
  find_package(rosidl_default_generators REQUIRED)
  foreach(dep ${VMI_DEPENDENCIES})
    find_package(${dep} REQUIRED)
  endforeach()
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module)
  # The PyPI wheels' exported targets name the include directory of the machine that built them.
  foreach(dep builtin_interfaces std_msgs geometry_msgs ${VMI_DEPENDENCIES})
    if(TARGET ${dep}::${dep}__rosidl_generator_py)
      set_target_properties(${dep}::${dep}__rosidl_generator_py PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${Python3_INCLUDE_DIRS}")
    endif()
  endforeach()
  rosidl_generate_interfaces(${PROJECT_NAME} ${VMI_MSGS} DEPENDENCIES ${VMI_DEPENDENCIES})
  ament_export_dependencies(rosidl_default_runtime)
  ament_package()
endmacro()
