/*
 * Frames for the port harnesses (tests/support/gateway_*_harness.c): a bus is one end of a
 * socketpair the port's code reads and writes as a CAN socket; the harness holds the other end.
 */
#ifndef CANERGY_TESTS_HARNESS_CAN_H
#define CANERGY_TESTS_HARNESS_CAN_H

/* A frame in candump's compact form ("18D01234#0A0B", the id hexadecimal, extended) sent into
 * sock, as if it came from the bus: exit 3 when it cannot be. */
void harness_frame_in(int sock, const char *text);

/* Every frame the port sent and sock holds, one line each on stdout: label, a space, then the
 * frame in candump's compact form; stdout flushed. */
void harness_print_sent(int sock, const char *label);

#endif /* CANERGY_TESTS_HARNESS_CAN_H */
