#include "e2e.h"

static uint8_t crc8_update(uint8_t crc, uint8_t byte)
{
    crc ^= byte;
    for (int bit = 0; bit < 8; ++bit) {
        crc = (uint8_t)((crc & 0x80u) ? (uint8_t)(crc << 1) ^ E2E_CRC8_POLY : (uint8_t)(crc << 1));
    }
    return crc;
}

uint8_t e2e_crc8(uint32_t data_id, const uint8_t *data, unsigned len)
{
    uint8_t crc = E2E_CRC8_INIT;
    crc = crc8_update(crc, (uint8_t)(data_id & 0xFFu));
    crc = crc8_update(crc, (uint8_t)((data_id >> 8) & 0xFFu));
    for (unsigned i = 1; i < len && i < E2E_MAX_FRAME_BYTES; ++i) {
        crc = crc8_update(crc, data[i]);
    }
    return (uint8_t)(crc ^ E2E_CRC8_XOR_OUT);
}

void e2e_protect(uint32_t data_id, uint8_t *data, unsigned len)
{
    data[0] = e2e_crc8(data_id, data, len);
}

bool e2e_crc_ok(uint32_t data_id, const uint8_t *data, unsigned len)
{
    return data[0] == e2e_crc8(data_id, data, len);
}

e2e_status e2e_check_counter(e2e_receiver *rx, uint8_t counter)
{
    counter &= (uint8_t)(E2E_COUNTER_MODULO - 1u);
    if (!rx->seen) {
        rx->seen = true;
        rx->last_counter = counter;
        return E2E_OK;
    }
    uint8_t delta = (uint8_t)((counter - rx->last_counter) & (E2E_COUNTER_MODULO - 1u));
    if (delta == 0u) {
        return E2E_REPEATED;
    }
    if (delta <= E2E_MAX_FORWARD_JUMP) {
        rx->last_counter = counter;
        rx->candidate_run = 0;
        return delta == 1u ? E2E_OK : E2E_OK_SOME_LOST;
    }
    uint8_t follows = (uint8_t)((rx->candidate + 1u) & (E2E_COUNTER_MODULO - 1u));
    rx->candidate_run = (rx->candidate_run > 0u && counter == follows) ? (uint8_t)(rx->candidate_run + 1u) : 1u;
    rx->candidate = counter;
    if (rx->candidate_run >= E2E_RESYNC_FRAMES) {
        rx->last_counter = counter;
        rx->candidate_run = 0;
        return E2E_OK_RESYNC;
    }
    return E2E_WRONG_SEQUENCE;
}
