/* Linux SocketCAN raw socket transport (the real one). */
#define _DEFAULT_SOURCE
#include <errno.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include "platform.h"

static int sock = -1;

int transport_open(const char *iface)
{
    struct ifreq ifr;
    struct sockaddr_can addr;
    if (strlen(iface) >= IFNAMSIZ) {
        fprintf(stderr, "policy_node: interface name too long: %s\n", iface);
        return -1;
    }
    sock = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (sock < 0) {
        fprintf(stderr, "policy_node: socket(PF_CAN): %s\n", strerror(errno));
        return -1;
    }
    memset(&ifr, 0, sizeof ifr);
    strncpy(ifr.ifr_name, iface, IFNAMSIZ - 1);
    if (ioctl(sock, SIOCGIFINDEX, &ifr) < 0) {
        fprintf(stderr, "policy_node: no CAN interface %s: %s\n", iface, strerror(errno));
        close(sock);
        sock = -1;
        return -1;
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(sock, (struct sockaddr *)&addr, sizeof addr) < 0) {
        fprintf(stderr, "policy_node: bind %s: %s\n", iface, strerror(errno));
        close(sock);
        sock = -1;
        return -1;
    }
    return 0;
}

int transport_recv(can_frame_t *frame, uint32_t timeout_ms)
{
    struct pollfd pfd = {sock, POLLIN, 0};
    struct can_frame raw;
    int ready = poll(&pfd, 1, (int)timeout_ms);
    if (ready == 0 || (ready < 0 && errno == EINTR)) {
        return 0;
    }
    if (ready < 0 || (pfd.revents & (POLLERR | POLLHUP | POLLNVAL))) {
        return -1;
    }
    ssize_t n = read(sock, &raw, sizeof raw);
    if (n != (ssize_t)sizeof raw) {
        return n < 0 && errno == EINTR ? 0 : -1;
    }
    frame->id = raw.can_id & CAN_EFF_MASK;
    frame->len = raw.can_dlc > 8u ? 8u : raw.can_dlc;
    memcpy(frame->data, raw.data, 8);
    if (raw.can_id & (CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG)) {
        frame->len = 0xFFu; /* extended, remote or error frames are never valid here */
    }
    return 1;
}

int transport_send(const can_frame_t *frame)
{
    struct can_frame raw;
    memset(&raw, 0, sizeof raw);
    raw.can_id = frame->id;
    raw.can_dlc = frame->len;
    memcpy(raw.data, frame->data, frame->len);
    return write(sock, &raw, sizeof raw) == (ssize_t)sizeof raw ? 0 : -1;
}

void transport_close(void)
{
    if (sock >= 0) {
        close(sock);
        sock = -1;
    }
}
