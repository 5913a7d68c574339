# Post-link checks of the STM32F405 image (run by the `image` target):
#  1. .bin and .hex from the .elf;
#  2. no heap: malloc/free/sbrk (and their reentrant forms) must not be in it;
#  3. flash (text + data) and static RAM (data + bss) within budget;
#  4. nothing loadable in the parameter sectors (_param_flash_start/_end of
#     stm32f405.ld: sectors 1 and 2), and the RAM functions (.ramfunc) in RAM;
#  5. the size report, written only when everything passed.
foreach(v ELF OUT_DIR OBJCOPY SIZE NM FLASH_BUDGET RAM_BUDGET)
  if(NOT DEFINED ${v})
    message(FATAL_ERROR "check_image.cmake: ${v} not set")
  endif()
endforeach()
get_filename_component(stem ${ELF} NAME_WE)
set(report ${OUT_DIR}/size-report.txt)
file(REMOVE ${report})

# The .bin spans the parameter sectors (the code starts after them): the gap
# reads as erased flash, so writing the .bin leaves them blank (defaults),
# never zeros (an invalid copy). `make flash` writes the .elf, which keeps them.
execute_process(COMMAND ${OBJCOPY} -O binary --gap-fill 0xff ${ELF} ${OUT_DIR}/${stem}.bin COMMAND_ERROR_IS_FATAL ANY)
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

# The parameter sectors: no loadable byte (program header PhysAddr..+FileSiz)
# may land in them, whatever the linker script says.
string(REGEX MATCH "([0-9a-fA-F]+) [A-Za-z] _param_flash_start\n" _ "${symbols}")
set(pstart "${CMAKE_MATCH_1}")
string(REGEX MATCH "([0-9a-fA-F]+) [A-Za-z] _param_flash_end\n" _ "${symbols}")
set(pend "${CMAKE_MATCH_1}")
if(pstart STREQUAL "" OR pend STREQUAL "")
  message(FATAL_ERROR "_param_flash_start/_param_flash_end missing from ${stem}.elf: the linker script must reserve the parameter sectors")
endif()
math(EXPR pstart "0x${pstart}")
math(EXPR pend "0x${pend}")
if(NOT DEFINED READELF OR READELF STREQUAL "")
  message(FATAL_ERROR "check_image.cmake: READELF not set")
endif()
execute_process(COMMAND ${READELF} -lW ${ELF} OUTPUT_VARIABLE phdrs COMMAND_ERROR_IS_FATAL ANY)
string(REGEX MATCHALL "LOAD +0x[0-9a-fA-F]+ +0x[0-9a-fA-F]+ +0x[0-9a-fA-F]+ +0x[0-9a-fA-F]+" loads "${phdrs}")
if(NOT loads)
  message(FATAL_ERROR "no LOAD program header in ${stem}.elf:\n${phdrs}")
endif()
foreach(l ${loads})
  string(REGEX MATCH "LOAD +0x[0-9a-fA-F]+ +0x[0-9a-fA-F]+ +(0x[0-9a-fA-F]+) +(0x[0-9a-fA-F]+)" _ "${l}")
  math(EXPR lo "${CMAKE_MATCH_1}")
  math(EXPR len "${CMAKE_MATCH_2}")
  math(EXPR hi "${lo} + ${len}")
  if(len GREATER 0 AND lo LESS pend AND hi GREATER pstart)
    message(FATAL_ERROR "${stem}.elf loads bytes at ${CMAKE_MATCH_1}+${CMAKE_MATCH_2}, inside the parameter sectors (${pstart}..${pend}): a parameter save would erase code")
  endif()
endforeach()
# Code that must run from RAM while the flash is busy (hal_flash.c).
if(symbols MATCHES "([0-9a-fA-F]+) [Tt] port_flash_ram_wait\n")
  math(EXPR ramfn "0x${CMAKE_MATCH_1}")
  if(ramfn LESS 536870912 OR ramfn GREATER_EQUAL 537001984) # 0x20000000 .. +128 KiB
    message(FATAL_ERROR "port_flash_ram_wait is at ${CMAKE_MATCH_1}, not in RAM: it would stall on the flash it waits for")
  endif()
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
# Berkeley's "text" counts every executable section, and .data now holds the
# RAM functions (.ramfunc): take .data's own size from the section list, so
# that it counts in flash (its initial image) and in RAM.
execute_process(COMMAND ${SIZE} -A -d ${ELF} OUTPUT_VARIABLE sections_out COMMAND_ERROR_IS_FATAL ANY)
if(sections_out MATCHES "\n[.]data[ \t]+([0-9]+)[ \t]+")
  set(data_sec ${CMAKE_MATCH_1})
  if(data_sec GREATER data)
    math(EXPR text "${text} - ${data_sec} + ${data}")
    set(data ${data_sec})
  endif()
endif()
math(EXPR flash "${text} + ${data}")
math(EXPR ram "${data} + ${bss}")
math(EXPR flash_pct "${flash} * 100 / ${FLASH_BUDGET}")
math(EXPR ram_pct "${ram} * 100 / ${RAM_BUDGET}")

set(text_report
"OIBAR STM32F405 image ${stem}.elf  (version ${VERSION}, build ${BUILD_ID})
  flash  ${flash} bytes (text ${text} + data ${data})  budget ${FLASH_BUDGET}  ${flash_pct}%
  params sectors 1-2 (0x08004000..0x0800BFFF) kept free; code from 0x0800C000
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
