# Post-link checks of the STM32F405 image (run by the `image` target):
#  1. .bin and .hex from the .elf;
#  2. no heap: malloc/free/sbrk (and their reentrant forms) must not be in it;
#  3. flash (text + data) and static RAM (data + bss) within budget;
#  4. the size report, written only when everything passed.
foreach(v ELF OUT_DIR OBJCOPY SIZE NM FLASH_BUDGET RAM_BUDGET)
  if(NOT DEFINED ${v})
    message(FATAL_ERROR "check_image.cmake: ${v} not set")
  endif()
endforeach()
get_filename_component(stem ${ELF} NAME_WE)
set(report ${OUT_DIR}/size-report.txt)
file(REMOVE ${report})

execute_process(COMMAND ${OBJCOPY} -O binary ${ELF} ${OUT_DIR}/${stem}.bin COMMAND_ERROR_IS_FATAL ANY)
execute_process(COMMAND ${OBJCOPY} -O ihex ${ELF} ${OUT_DIR}/${stem}.hex COMMAND_ERROR_IS_FATAL ANY)

execute_process(COMMAND ${NM} -g --defined-only ${ELF}
                OUTPUT_VARIABLE symbols COMMAND_ERROR_IS_FATAL ANY)
set(found "")
foreach(sym malloc free calloc realloc _malloc_r _free_r _calloc_r _realloc_r _sbrk _sbrk_r sbrk)
  if(symbols MATCHES "[ \t]${sym}\n")
    list(APPEND found ${sym})
  endif()
endforeach()
if(found)
  message(FATAL_ERROR "heap allocator linked into ${stem}.elf: ${found} (nothing may allocate; see the .map for who pulls it in)")
endif()

# Berkeley format: text data bss dec hex filename
execute_process(COMMAND ${SIZE} -B -d ${ELF} OUTPUT_VARIABLE size_out COMMAND_ERROR_IS_FATAL ANY)
string(REGEX MATCH "\n[ \t]*([0-9]+)[ \t]+([0-9]+)[ \t]+([0-9]+)" _ "${size_out}")
set(text ${CMAKE_MATCH_1})
set(data ${CMAKE_MATCH_2})
set(bss ${CMAKE_MATCH_3})
if(text STREQUAL "")
  message(FATAL_ERROR "could not parse `size` output:\n${size_out}")
endif()
math(EXPR flash "${text} + ${data}")
math(EXPR ram "${data} + ${bss}")
math(EXPR flash_pct "${flash} * 100 / ${FLASH_BUDGET}")
math(EXPR ram_pct "${ram} * 100 / ${RAM_BUDGET}")

set(text_report
"OIBAR STM32F405 image ${stem}.elf  (version ${VERSION}, build ${BUILD_ID})
  flash  ${flash} bytes (text ${text} + data ${data})  budget ${FLASH_BUDGET}  ${flash_pct}%
  RAM    ${ram} bytes (data ${data} + bss ${bss}, stack not included)  budget ${RAM_BUDGET}  ${ram_pct}%
  heap   none (no malloc/free/sbrk in the image)
  files  ${stem}.elf ${stem}.bin ${stem}.hex ${stem}.map
")
set(over "")
if(flash GREATER FLASH_BUDGET)
  string(APPEND over "flash ${flash} > ${FLASH_BUDGET} bytes; ")
endif()
if(ram GREATER RAM_BUDGET)
  string(APPEND over "static RAM ${ram} > ${RAM_BUDGET} bytes; ")
endif()
if(over)
  message(FATAL_ERROR "${text_report}OVER BUDGET: ${over}")
endif()
file(WRITE ${report} "${text_report}")
