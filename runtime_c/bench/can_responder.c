/* The trivial responder of `embedrl hil bench`: the bus's floor, without a policy.
 *
 *   can_responder IFACE FIRST_ID COUNT REPLY_ID REPLY_LEN
 *
 * It receives the COUNT frames FIRST_ID .. FIRST_ID + COUNT - 1 (hex; a step's observation frames, as the
 * node's kernel filter passes them) and answers the last of them at once with one frame of REPLY_ID (hex)
 * and REPLY_LEN zero bytes (a classic frame, at most 8): the same frames out and back as a lock-step
 * exchange with the node, with no decoding, no check and no inference in between. Runs until killed. */
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

#define MAX_FRAMES 64u

static int usage(void)
{
    fprintf(stderr, "usage: can_responder IFACE FIRST_ID COUNT REPLY_ID REPLY_LEN (ids in hex, length 0..8)\n");
    return 2;
}

int main(int argc, char **argv)
{
    if (argc != 6 || strlen(argv[1]) >= IFNAMSIZ) {
        return usage();
    }
    char *end = NULL;
    const unsigned long first = strtoul(argv[2], &end, 16);
    const unsigned long count = strtoul(argv[3], &end, 10);
    const unsigned long reply_id = strtoul(argv[4], &end, 16);
    const long reply_len = strtol(argv[5], &end, 10);
    if (count < 1u || count > MAX_FRAMES || first + count - 1u > CAN_SFF_MASK || reply_id > CAN_SFF_MASK ||
        reply_len < 0 || reply_len > CAN_MAX_DLEN) {
        return usage();
    }
    const canid_t last = (canid_t)(first + count - 1u);
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
    struct can_filter filters[MAX_FRAMES];
    for (unsigned long k = 0u; k < count; ++k) {
        filters[k].can_id = (canid_t)(first + k);
        filters[k].can_mask = CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
    }
    (void)setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, filters, (socklen_t)(count * sizeof filters[0]));
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
        if (frame.can_id != last) {
            continue;
        }
        if (write(sock, &reply, sizeof reply) != (ssize_t)sizeof reply) {
            perror("write");
            return 1;
        }
    }
}
