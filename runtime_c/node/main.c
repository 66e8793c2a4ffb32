/*
 * policy_node --iface vcan0 [--timeout-ms T] [--recover K] [--status-ms P]
 *
 * Runs the policy as a CAN node until SIGTERM/SIGINT (exit 0) or until the interface fails (exit 1).
 */
#define _POSIX_C_SOURCE 199309L
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "node.h"

#define DEFAULT_RECOVER 3u

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

static int usage(void)
{
    fprintf(stderr, "usage: policy_node --iface NAME [--timeout-ms 1..60000] [--recover 1..1000] "
                    "[--status-ms 10..60000]\n");
    return 2;
}

int main(int argc, char **argv)
{
    const char *iface = NULL;
    node_config config = {POLICY_IO_WATCHDOG_MS, DEFAULT_RECOVER, POLICY_IO_STATUS_PERIOD_MS};
    for (int i = 1; i < argc; ++i) {
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
    if (transport_open(iface) != 0) {
        return 1;
    }
    node_t node;
    node_init(&node, &config, clock_ms());
    int status = 0;
    while (!stop) {
        uint32_t wait_ms = node_poll(&node, clock_ms());
        can_frame_t frame;
        int got = transport_recv(&frame, wait_ms);
        if (got < 0) {
            fprintf(stderr, "policy_node: CAN interface %s failed\n", iface);
            status = 1;
            break;
        }
        if (got > 0) {
            node_on_frame(&node, &frame, clock_ms());
        }
    }
    transport_close();
    return status;
}
