/* Fake transport and clock for the node's unit tests: sent frames are recorded, time is set by hand. */
#include "fake_platform.h"

#include <string.h>

static can_frame_t sent[FAKE_MAX_SENT];
static unsigned sent_count;
static uint32_t now_us;
static bool sends_fail;

int transport_open(const char *iface, const uint32_t *ids, unsigned count, int fd)
{
    (void)iface;
    (void)ids;
    (void)count;
    (void)fd;
    return 0;
}

transport_event transport_recv(can_frame_t *frame, uint8_t *bus_state, uint32_t timeout_ms)
{
    (void)frame;
    (void)bus_state;
    (void)timeout_ms;
    return TRANSPORT_TIMEOUT;
}

int transport_send(const can_frame_t *frame)
{
    if (sends_fail) {
        return -1;
    }
    if (sent_count < FAKE_MAX_SENT) {
        sent[sent_count++] = *frame;
    }
    return 0;
}

const char *transport_error(void)
{
    return "";
}

void sleep_ms(uint32_t ms)
{
    now_us += ms * 1000u;
}

void fake_fail_sends(bool fail)
{
    sends_fail = fail;
}

void transport_close(void)
{
}

uint32_t clock_ms(void)
{
    return now_us / 1000u;
}

uint32_t clock_us(void)
{
    return now_us;
}

void fake_reset(void)
{
    sent_count = 0;
    memset(sent, 0, sizeof sent);
}

unsigned fake_sent_count(void)
{
    return sent_count;
}

const can_frame_t *fake_sent(unsigned index)
{
    return index < sent_count ? &sent[index] : NULL;
}

void fake_set_ms(uint32_t ms)
{
    now_us = ms * 1000u;
}
