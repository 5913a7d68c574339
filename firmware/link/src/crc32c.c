/* CRC-32C with a nibble table: small flash, plenty fast at UART speeds. */
#include "oibar/crc32c.h"

#include "oibar/assert.h"

/* table[n] = CRC register contribution of the low nibble n after four
 * reflected shifts with polynomial 0x82F63B78. */
static const uint32_t crc32c_nibble_table[16] = {
    0x00000000u, 0x105EC76Fu, 0x20BD8EDEu, 0x30E349B1u,
    0x417B1DBCu, 0x5125DAD3u, 0x61C69362u, 0x7198540Du,
    0x82F63B78u, 0x92A8FC17u, 0xA24BB5A6u, 0xB21572C9u,
    0xC38D26C4u, 0xD3D3E1ABu, 0xE330A81Au, 0xF36E6F75u,
};

uint32_t oibar_crc32c_init(void)
{
    return 0xFFFFFFFFu;
}

uint32_t oibar_crc32c_update(uint32_t crc, const uint8_t *data, size_t len)
{
    OIBAR_ASSERT(data != NULL || len == 0u);
    for (size_t i = 0u; i < len; ++i) {
        crc ^= data[i];
        crc = (crc >> 4) ^ crc32c_nibble_table[crc & 0x0Fu];
        crc = (crc >> 4) ^ crc32c_nibble_table[crc & 0x0Fu];
    }
    return crc;
}

uint32_t oibar_crc32c_final(uint32_t crc)
{
    return crc ^ 0xFFFFFFFFu;
}

uint32_t oibar_crc32c(const uint8_t *data, size_t len)
{
    return oibar_crc32c_final(oibar_crc32c_update(oibar_crc32c_init(), data, len));
}
