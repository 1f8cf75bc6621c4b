/* Minimal cosurg UDP bridge driver (docs/haptics.md): poses out, forces in.
 * Assumes a little-endian host (x86-64, ARM64). Build: cc -O2 -o udp_driver udp_driver.c */
#include <arpa/inet.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

static uint64_t now_us(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

int main(void) {
    int s = socket(AF_INET, SOCK_DGRAM, 0);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons(7701)};
    inet_pton(AF_INET, "127.0.0.1", &a.sin_addr);
    connect(s, (struct sockaddr *)&a, sizeof a);
    for (uint32_t seq = 1; seq <= 2000; seq++) {
        uint8_t p[84] = {'C', 'S', 'G', 'P'};
        uint64_t t = now_us();
        double pos[3] = {0.0, 0.0, -0.002}; /* read these from the device */
        double quat[4] = {1.0, 0.0, 0.0, 0.0}, jaw = 0.0;
        uint32_t buttons = 0;
        memcpy(p + 4, &seq, 4);
        memcpy(p + 8, &t, 8);
        memcpy(p + 16, pos, 24);
        memcpy(p + 40, quat, 32);
        memcpy(p + 72, &jaw, 8);
        memcpy(p + 80, &buttons, 4);
        send(s, p, sizeof p, 0);
        uint8_t f[72], buf[72];
        int got = 0; /* drain the socket: the newest force wins */
        while (recv(s, buf, sizeof buf, MSG_DONTWAIT) == 72)
            if (memcmp(buf, "CSGF", 4) == 0) memcpy(f, buf, 72), got = 1;
        if (got) {
            double force[3];
            uint32_t echo, flags;
            memcpy(&echo, f + 8, 4);
            memcpy(&flags, f + 12, 4);
            memcpy(force, f + 24, 24);
            if (seq % 500 == 0)
                printf("seq %u echo %u flags %u force %.3f %.3f %.3f N\n", seq, echo, flags,
                       force[0], force[1], force[2]);
            /* device_set_force(force); */
        }
        usleep(1000);
    }
    return 0;
}
