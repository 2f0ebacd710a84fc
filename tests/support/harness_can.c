/*
 * Frames for the port harnesses (harness_can.h).
 */
#define _GNU_SOURCE 1

#include "harness_can.h"

#include <linux/can.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>

void harness_frame_in(int sock, const char *text)
{
    struct canfd_frame cf;
    memset(&cf, 0, sizeof cf);
    char *end = NULL;
    cf.can_id = (canid_t)strtoul(text, &end, 16) | CAN_EFF_FLAG;
    const char *hex = end != NULL && *end == '#' ? end + 1 : "";
    while (cf.len < CANFD_MAX_DLEN && hex[0] != '\0' && hex[0] != '\n' && hex[1] != '\0') {
        const char byte[3] = {hex[0], hex[1], '\0'};
        cf.data[cf.len++] = (uint8_t)strtoul(byte, NULL, 16);
        hex += 2;
    }
    const size_t size = cf.len > CAN_MAX_DLEN ? CANFD_MTU : CAN_MTU;
    if (send(sock, &cf, size, 0) != (ssize_t)size) {
        exit(3);
    }
}

void harness_print_sent(int sock, const char *label)
{
    struct canfd_frame cf;
    while (recv(sock, &cf, sizeof cf, MSG_DONTWAIT) > 0) {
        (void)printf("%s %08X#", label, (unsigned)(cf.can_id & CAN_EFF_MASK));
        for (unsigned i = 0U; i < cf.len; i++) {
            (void)printf("%02X", (unsigned)cf.data[i]);
        }
        (void)printf("\n");
    }
    (void)fflush(stdout);
}
