/* The trivial responder of `embedrl hil bench`: the bus's floor, without a policy.
 *
 *   can_responder IFACE TRIGGER_ID REPLY_ID REPLY_LEN
 *
 * Every frame with TRIGGER_ID (hex; a step's last observation frame) is answered at once with one frame of
 * REPLY_ID (hex) and REPLY_LEN zero bytes (a classic frame, at most 8): the same frames out and back as a
 * lock-step exchange with the node, with no decoding, no check and no inference in between. It reads only
 * TRIGGER_ID (a kernel filter) and runs until killed. */
#define _DEFAULT_SOURCE
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

static int usage(void)
{
    fprintf(stderr, "usage: can_responder IFACE TRIGGER_ID REPLY_ID REPLY_LEN (ids in hex, length 0..8)\n");
    return 2;
}

int main(int argc, char **argv)
{
    if (argc != 5 || strlen(argv[1]) >= IFNAMSIZ) {
        return usage();
    }
    char *end = NULL;
    const unsigned long trigger = strtoul(argv[2], &end, 16);
    const unsigned long reply_id = strtoul(argv[3], &end, 16);
    const long reply_len = strtol(argv[4], &end, 10);
    if (trigger > CAN_SFF_MASK || reply_id > CAN_SFF_MASK || reply_len < 0 || reply_len > CAN_MAX_DLEN) {
        return usage();
    }
    const int sock = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (sock < 0) {
        perror("socket(PF_CAN)");
        return 1;
    }
    struct ifreq ifr;
    memset(&ifr, 0, sizeof ifr);
    strncpy(ifr.ifr_name, argv[1], IFNAMSIZ - 1);
    if (ioctl(sock, SIOCGIFINDEX, &ifr) < 0) {
        perror(argv[1]);
        return 1;
    }
    struct can_filter filter = {(canid_t)trigger, CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG};
    (void)setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, &filter, sizeof filter);
    struct sockaddr_can addr;
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(sock, (struct sockaddr *)&addr, sizeof addr) < 0) {
        perror("bind");
        return 1;
    }
    struct can_frame reply;
    memset(&reply, 0, sizeof reply);
    reply.can_id = (canid_t)reply_id;
    reply.can_dlc = (__u8)reply_len;
    printf("ready\n");
    fflush(stdout);
    for (;;) {
        struct can_frame frame;
        if (read(sock, &frame, sizeof frame) < 0) {
            perror("read");
            return 1;
        }
        if (write(sock, &reply, sizeof reply) != (ssize_t)sizeof reply) {
            perror("write");
            return 1;
        }
    }
}
