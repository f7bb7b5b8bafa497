/* The reference client for benches/acquire_ratio.sh: libmodbus reads the same block as the
 * service (input registers START..START+COUNT of UNIT, one modbus_read_input_registers per
 * block, one request in flight, as libmodbus does) in a loop for SECONDS, then prints
 * "BLOCKS SECONDS ERRORS". Built by the bench against a libmodbus it fetched itself.
 *   libmodbus_read HOST PORT UNIT START COUNT SECONDS */
#include <errno.h>
#include <modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

int main(int argc, char **argv) {
    if (argc != 7) {
        fprintf(stderr, "usage: %s HOST PORT UNIT START COUNT SECONDS\n", argv[0]);
        return 2;
    }
    int port = atoi(argv[2]), unit = atoi(argv[3]), start = atoi(argv[4]);
    int count = atoi(argv[5]);
    double secs = atof(argv[6]);
    if (count < 1 || count > 125) {
        fprintf(stderr, "COUNT must be 1..125, not %s\n", argv[5]);
        return 2;
    }
    modbus_t *ctx = modbus_new_tcp(argv[1], port);
    if (ctx == NULL || modbus_set_slave(ctx, unit) != 0 || modbus_connect(ctx) != 0) {
        fprintf(stderr, "cannot connect to %s:%d: %s\n", argv[1], port, modbus_strerror(errno));
        return 1;
    }
    uint16_t regs[125];
    long blocks = 0, errors = 0;
    double t0 = now(), t = t0;
    while (t - t0 < secs) {
        /* The clock read every 64 blocks: the loop is the library's, not ours. */
        for (int k = 0; k < 64; k++) {
            if (modbus_read_input_registers(ctx, start, count, regs) == count) {
                blocks++;
            } else {
                /* A late reply (a timeout) would answer the next request: drop what is
                 * pending, as libmodbus's manual advises, so one error stays one. */
                errors++;
                modbus_flush(ctx);
            }
        }
        t = now();
    }
    printf("%ld %.3f %ld\n", blocks, t - t0, errors);
    modbus_close(ctx);
    modbus_free(ctx);
    return errors == 0 ? 0 : 1;
}
