/*
 * policy_node --iface vcan0 [--timeout-ms T] [--recover K] [--status-ms P] [--node-id N]
 *
 * Runs the policy as a CAN node until SIGTERM/SIGINT (exit 0). An interface that cannot be opened at
 * start is an error (exit 1); one that fails later (link down, interface removed) puts the node in SAFE
 * and is re-opened every REOPEN_MS until it is back: the node never exits on its own.
 */
#define _POSIX_C_SOURCE 199309L
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "node.h"

#define DEFAULT_RECOVER 3u
#define REOPEN_MS 100u

static volatile sig_atomic_t stop;

static void on_signal(int sig)
{
    (void)sig;
    stop = 1;
}

static int parse_u32(const char *text, uint32_t min, uint32_t max, uint32_t *out)
{
    char *end = NULL;
    unsigned long v = strtoul(text, &end, 10);
    if (end == text || *end != '\0' || v < min || v > max) {
        return -1;
    }
    *out = (uint32_t)v;
    return 0;
}

/* The interface failed: SAFE, then wait for it and open it again (or stop on a signal). */
static void reopen(node_t *node, const char *iface, const uint32_t *ids)
{
    fprintf(stderr, "policy_node: CAN interface %s failed; SAFE until it is back\n", iface);
    transport_close();
    node_link_lost(node, clock_ms());
    while (!stop && transport_open(iface, ids, NODE_RX_IDS, POLICY_IO_FD) != 0) {
        (void)node_poll(node, clock_ms()); /* status and safe action go nowhere: counted as send failures */
        sleep_ms(REOPEN_MS);
    }
    if (!stop) {
        fprintf(stderr, "policy_node: CAN interface %s re-opened\n", iface);
        node_link_restored(node, clock_ms());
    }
}

static void print_usage(FILE *to)
{
    fprintf(to, "usage: policy_node --iface NAME [--timeout-ms 1..60000] [--recover 1..1000] "
                "[--status-ms 10..60000] [--node-id 0..%u]\n",
            POLICY_IO_MAX_NODES - 1u);
}

static int usage(void)
{
    print_usage(stderr);
    return 2;
}

int main(int argc, char **argv)
{
    const char *iface = NULL;
    node_config config = {POLICY_IO_WATCHDOG_MS, DEFAULT_RECOVER, POLICY_IO_STATUS_PERIOD_MS, 0u};
    for (int i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--help") == 0 || strcmp(argv[i], "-h") == 0) {
            print_usage(stdout); /* asked for: on stdout, success */
            return 0;
        }
        if (i + 1 >= argc) {
            return usage();
        }
        const char *value = argv[++i];
        if (strcmp(argv[i - 1], "--iface") == 0) {
            iface = value;
        } else if (strcmp(argv[i - 1], "--timeout-ms") == 0) {
            if (parse_u32(value, 1u, 60000u, &config.timeout_ms) != 0) {
                return usage();
            }
        } else if (strcmp(argv[i - 1], "--recover") == 0) {
            if (parse_u32(value, 1u, 1000u, &config.recover_count) != 0) {
                return usage();
            }
        } else if (strcmp(argv[i - 1], "--node-id") == 0) {
            if (parse_u32(value, 0u, POLICY_IO_MAX_NODES - 1u, &config.node_id) != 0) {
                return usage();
            }
        } else if (strcmp(argv[i - 1], "--status-ms") == 0) {
            if (parse_u32(value, 10u, 60000u, &config.status_period_ms) != 0) {
                return usage();
            }
        } else {
            return usage();
        }
    }
    if (iface == NULL) {
        return usage();
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    uint32_t ids[NODE_RX_IDS];
    node_receive_ids(config.node_id, ids);
    if (transport_open(iface, ids, NODE_RX_IDS, POLICY_IO_FD) != 0) {
        fprintf(stderr, "policy_node: %s\n", transport_error());
        return 1;
    }
    node_t node;
    node_init(&node, &config, clock_ms());
    /* One clock read per wake-up, used for the frame and for the next wait: a read is a system call on
     * some kernels (User-Mode Linux: ~70 us), and the handling in between takes microseconds. */
    uint32_t now = clock_ms();
    while (!stop) {
        uint32_t wait_ms = node_poll(&node, now);
        can_frame_t frame;
        uint8_t bus_state = 0;
        transport_event event = transport_recv(&frame, &bus_state, wait_ms);
        now = clock_ms();
        if (event == TRANSPORT_FRAME) {
            node_on_frame(&node, &frame, now);
        } else if (event == TRANSPORT_BUS_STATE) {
            node_on_bus_state(&node, (node_bus_state)bus_state);
        } else if (event == TRANSPORT_FAILED) {
            reopen(&node, iface, ids);
            now = clock_ms();
        }
    }
    transport_close();
    return 0;
}
