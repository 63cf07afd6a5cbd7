#!/usr/bin/env bash
# What touching fresh memory costs on this machine, apart from mlsss: a small C program maps
# SIZE MiB, touches every 4 KiB page on one or two threads, in huge pages (MADV_HUGEPAGE) or
# small ones, and prints the wall time. Each case runs after a pause of PAUSE seconds (memory the
# guest freed earlier has by then been reported to a hypervisor that takes it back, where the
# kernel does free page reporting) and again at once (memory freed a moment before).
#
#   scripts/fresh_memory_cost.sh [SIZE_MIB] [ROUNDS] [PAUSE_S]     (defaults 512 3 6)
#
# On the 2-core build VM (2026-12-01, free page reporting with min_free_ms=0): 512 MiB after a
# pause took 1.03-1.21 s on one thread in huge pages and 0.23-0.37 s in small ones; 1 GiB again
# at once 0.05-0.16 s. See README "What to expect". Needs a C compiler (cc).
set -euo pipefail
SIZE=${1:-512}
ROUNDS=${2:-3}
PAUSE=${3:-6}
command -v cc >/dev/null || { echo "error: no C compiler (cc): apt-get install gcc" >&2; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cat > "$work/touch.c" <<'EOF'
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>

static size_t per_thread;
static int huge;

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

static void *touch(void *unused) {
    (void)unused;
    char *p = mmap(0, per_thread, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) { perror("mmap"); exit(1); }
    madvise(p, per_thread, huge ? MADV_HUGEPAGE : MADV_NOHUGEPAGE);
    for (size_t i = 0; i < per_thread; i += 4096) p[i] = 1;
    munmap(p, per_thread);
    return 0;
}

int main(int argc, char **argv) {
    if (argc != 4) { fprintf(stderr, "usage: touch THREADS MIB HUGE\n"); return 2; }
    int threads = atoi(argv[1]);
    size_t total = (size_t)atol(argv[2]) << 20;
    huge = atoi(argv[3]);
    if (threads < 1 || threads > 16) { fprintf(stderr, "1 to 16 threads\n"); return 2; }
    per_thread = total / threads;
    pthread_t t[16];
    double t0 = now();
    for (int i = 0; i < threads; i++) pthread_create(&t[i], 0, touch, 0);
    for (int i = 0; i < threads; i++) pthread_join(t[i], 0);
    printf("%.3f", now() - t0);
    return 0;
}
EOF
cc -O2 -pthread -o "$work/touch" "$work/touch.c"
printf "%-6s %-7s %-7s %14s %14s\n" round threads pages "after pause s" "again at once s"
for round in $(seq "$ROUNDS"); do
    for threads in 1 2; do
        for huge in 1 0; do
            sleep "$PAUSE"
            first=$("$work/touch" "$threads" "$SIZE" "$huge")
            again=$("$work/touch" "$threads" "$SIZE" "$huge")
            printf "%-6s %-7s %-7s %14s %14s\n" "$round" "$threads" "$([ "$huge" = 1 ] && echo huge || echo small)" "$first" "$again"
        done
    done
done
echo "($SIZE MiB touched each time, ${PAUSE} s pause before each pair)"
