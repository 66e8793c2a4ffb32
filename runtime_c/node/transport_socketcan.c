/* Linux SocketCAN raw socket transport (the real one). */
#define _DEFAULT_SOURCE
#include <errno.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include "platform.h"

#define MAX_FILTERS 64u
#define BUS_ACTIVE 0u
#define BUS_PASSIVE 1u
#define BUS_OFF 2u

#ifndef CAN_ERR_CRTL_ACTIVE
#define CAN_ERR_CRTL_ACTIVE 0x40 /* linux/can/error.h since 4.x: back to error active */
#endif

static int sock = -1;
static char error_text[160];

static int fail(const char *what, const char *iface)
{
    snprintf(error_text, sizeof error_text, "%s %s: %s", what, iface, strerror(errno));
    if (sock >= 0) {
        close(sock);
        sock = -1;
    }
    return -1;
}

const char *transport_error(void)
{
    return error_text;
}

static int fd_frames;

int transport_open(const char *iface, const uint32_t *ids, unsigned count, int fd)
{
    struct ifreq ifr;
    struct sockaddr_can addr;
    struct can_filter filters[MAX_FILTERS];
    if (strlen(iface) >= IFNAMSIZ || count == 0u || count > MAX_FILTERS) {
        errno = EINVAL;
        return fail("cannot open", iface);
    }
    sock = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (sock < 0) {
        return fail("socket(PF_CAN) for", iface);
    }
    memset(&ifr, 0, sizeof ifr);
    strncpy(ifr.ifr_name, iface, IFNAMSIZ - 1);
    if (ioctl(sock, SIOCGIFFLAGS, &ifr) < 0) {
        return fail("no CAN interface", iface);
    }
    if (!(ifr.ifr_flags & IFF_UP)) {
        errno = ENETDOWN;
        return fail("interface down:", iface);
    }
    if (ioctl(sock, SIOCGIFINDEX, &ifr) < 0) {
        return fail("no CAN interface", iface);
    }
    /* Only our standard-ID data frames wake the node: a flood of other IDs stays in the kernel. */
    for (unsigned i = 0; i < count; ++i) {
        filters[i].can_id = ids[i];
        filters[i].can_mask = CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
    }
    can_err_mask_t err_mask = CAN_ERR_BUSOFF | CAN_ERR_CRTL | CAN_ERR_RESTARTED;
    if (setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, filters, (socklen_t)(count * sizeof filters[0])) < 0 ||
        setsockopt(sock, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &err_mask, sizeof err_mask) < 0) {
        return fail("CAN_RAW_FILTER on", iface);
    }
    fd_frames = fd != 0;
    if (fd_frames) {
        int on = 1;
        if (setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &on, sizeof on) < 0) {
            return fail("CAN FD (CAN_RAW_FD_FRAMES) on", iface);
        }
        if (ioctl(sock, SIOCGIFMTU, &ifr) < 0 || ifr.ifr_mtu != (int)CANFD_MTU) {
            errno = EPROTONOSUPPORT;
            return fail("not a CAN FD interface (its MTU must be 72):", iface);
        }
        if (ioctl(sock, SIOCGIFINDEX, &ifr) < 0) {
            return fail("no CAN interface", iface);
        }
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(sock, (struct sockaddr *)&addr, sizeof addr) < 0) {
        return fail("bind", iface);
    }
    return 0;
}

/* The controller state an error frame announces; -1 if it announces none. */
static int bus_state_of(const struct can_frame *raw)
{
    if (raw->can_id & CAN_ERR_BUSOFF) {
        return BUS_OFF;
    }
    if (raw->can_id & CAN_ERR_RESTARTED) {
        return BUS_ACTIVE;
    }
    if (raw->can_id & CAN_ERR_CRTL) {
        if (raw->data[1] & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE)) {
            return BUS_PASSIVE;
        }
        if (raw->data[1] & CAN_ERR_CRTL_ACTIVE) {
            return BUS_ACTIVE;
        }
    }
    return -1;
}

transport_event transport_recv(can_frame_t *frame, uint8_t *bus_state, uint32_t timeout_ms)
{
    struct pollfd pfd = {sock, POLLIN, 0};
    struct canfd_frame raw; /* a classic frame arrives as CAN_MTU bytes of the same layout */
    int ready = poll(&pfd, 1, (int)timeout_ms);
    if (ready == 0 || (ready < 0 && errno == EINTR)) {
        return TRANSPORT_TIMEOUT;
    }
    if (ready < 0 || (pfd.revents & (POLLERR | POLLHUP | POLLNVAL))) {
        return TRANSPORT_FAILED; /* e.g. ENETDOWN after `ip link set ... down` */
    }
    memset(&raw, 0, sizeof raw);
    ssize_t n = read(sock, &raw, sizeof raw);
    if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) {
        return n < 0 && errno == EINTR ? TRANSPORT_TIMEOUT : TRANSPORT_FAILED;
    }
    if (raw.can_id & CAN_ERR_FLAG) {
        int state = bus_state_of((const struct can_frame *)(const void *)&raw);
        if (state < 0) {
            return TRANSPORT_TIMEOUT;
        }
        *bus_state = (uint8_t)state;
        return TRANSPORT_BUS_STATE;
    }
    unsigned max = n == (ssize_t)CANFD_MTU ? CANFD_MAX_DLEN : CAN_MAX_DLEN;
    frame->id = raw.can_id & CAN_EFF_MASK;
    frame->len = (uint8_t)(raw.len > max ? max : raw.len);
    memcpy(frame->data, raw.data, max);
    if (raw.can_id & (CAN_EFF_FLAG | CAN_RTR_FLAG)) {
        frame->len = 0xFFu; /* extended or remote frames are never valid here */
    }
    return TRANSPORT_FRAME;
}

int transport_send(const can_frame_t *frame)
{
    struct canfd_frame raw;
    if (sock < 0 || frame->len > CANFD_MAX_DLEN) {
        return -1;
    }
    memset(&raw, 0, sizeof raw);
    raw.can_id = frame->id;
    raw.len = frame->len;
    memcpy(raw.data, frame->data, frame->len);
    size_t size = frame->len > CAN_MAX_DLEN ? CANFD_MTU : CAN_MTU; /* longer than 8 bytes: an FD frame */
    return write(sock, &raw, size) == (ssize_t)size ? 0 : -1;
}

void transport_close(void)
{
    if (sock >= 0) {
        close(sock);
        sock = -1;
    }
}
