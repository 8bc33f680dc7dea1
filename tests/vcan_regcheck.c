/* vcan_regcheck.c: do vector registers survive context switches? (tests/test_vcan_sandbox.py)
 *
 * Several threads of one process each load distinct values into the widest vector
 * registers the CPU has (zmm0-31 with AVX-512F, else ymm0-15 with AVX, else xmm0-15),
 * then, without touching them, busy-spin and call sched_yield() in a loop, so that the
 * kernel (in the vcan sandbox: User-Mode Linux, which saves and restores every task's
 * registers through ptrace and, where needed, scripts/uml-xsave-shim.c) switches between
 * them and preempts them; then store the registers and compare. New values every round.
 *
 *   vcan_regcheck [--seconds S] [--threads N] [--width 512|256|128] [--clobber]
 *
 * --clobber: thread 0 overwrites register 7 after its loop in every round, as a broken
 * save/restore would: the checker must count one corruption per round of that thread.
 * Prints one line "regcheck: width W bits, R registers, ... corruptions C"; exit status 0
 * when C == 0, 1 otherwise, 2 on bad usage.
 */
#define _GNU_SOURCE
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>

#define MAXREGS 32
#define MAXBYTES 64
#define MAXTHREADS 16

#define ALL16(M) M(0) M(1) M(2) M(3) M(4) M(5) M(6) M(7) \
                 M(8) M(9) M(10) M(11) M(12) M(13) M(14) M(15)
#define HI16(M) M(16) M(17) M(18) M(19) M(20) M(21) M(22) M(23) \
                M(24) M(25) M(26) M(27) M(28) M(29) M(30) M(31)

/* The loop between load and store: spin, then sched_yield (syscall 24), iters times.
 * The syscall clobbers rax, rcx, r11 only; vector registers are the task's to keep. */
#define LOOP                                   \
    "2:\n\t"                                   \
    "mov %[spin], %%rcx\n\t"                   \
    "3:\n\t"                                   \
    "dec %%rcx\n\t"                            \
    "jnz 3b\n\t"                               \
    "mov $24, %%eax\n\t"                       \
    "syscall\n\t"                              \
    "dec %[iters]\n\t"                         \
    "jnz 2b\n\t"                               \
    "test %[clob], %[clob]\n\t"                \
    "jz 4f\n\t"

#define XCLOB "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", \
    "xmm9", "xmm10", "xmm11", "xmm12", "xmm13", "xmm14", "xmm15"
#define ZCLOB "xmm16", "xmm17", "xmm18", "xmm19", "xmm20", "xmm21", "xmm22", "xmm23", \
    "xmm24", "xmm25", "xmm26", "xmm27", "xmm28", "xmm29", "xmm30", "xmm31"

#define LDZ(n) "vmovdqu64 " #n "*64(%[in]), %%zmm" #n "\n\t"
#define STZ(n) "vmovdqu64 %%zmm" #n ", " #n "*64(%[out])\n\t"
__attribute__((target("avx512f"))) static void
run_zmm(const void *in, void *out, long iters, long spin, long clob)
{
    __asm__ volatile(ALL16(LDZ) HI16(LDZ) LOOP
                     "vpternlogd $0xff, %%zmm7, %%zmm7, %%zmm7\n\t"
                     "4:\n\t" ALL16(STZ) HI16(STZ)
                     : [iters] "+r"(iters)
                     : [in] "r"(in), [out] "r"(out), [spin] "r"(spin), [clob] "r"(clob)
                     : "rax", "rcx", "r11", "memory", "cc", XCLOB, ZCLOB);
}

#define LDY(n) "vmovdqu " #n "*64(%[in]), %%ymm" #n "\n\t"
#define STY(n) "vmovdqu %%ymm" #n ", " #n "*64(%[out])\n\t"
__attribute__((target("avx"))) static void
run_ymm(const void *in, void *out, long iters, long spin, long clob)
{
    __asm__ volatile(ALL16(LDY) LOOP
                     "vpcmpeqd %%xmm7, %%xmm7, %%xmm7\n\t"  /* ymm7 = 1s in low, 0 high */
                     "4:\n\t" ALL16(STY) "vzeroupper\n\t"
                     : [iters] "+r"(iters)
                     : [in] "r"(in), [out] "r"(out), [spin] "r"(spin), [clob] "r"(clob)
                     : "rax", "rcx", "r11", "memory", "cc", XCLOB);
}

#define LDX(n) "movdqu " #n "*64(%[in]), %%xmm" #n "\n\t"
#define STX(n) "movdqu %%xmm" #n ", " #n "*64(%[out])\n\t"
static void run_xmm(const void *in, void *out, long iters, long spin, long clob)
{
    __asm__ volatile(ALL16(LDX) LOOP
                     "pcmpeqd %%xmm7, %%xmm7\n\t"
                     "4:\n\t" ALL16(STX)
                     : [iters] "+r"(iters)
                     : [in] "r"(in), [out] "r"(out), [spin] "r"(spin), [clob] "r"(clob)
                     : "rax", "rcx", "r11", "memory", "cc", XCLOB);
}

static int width, nregs, clobber;
static double seconds = 2.0;
static long spin = 100000, iters = 20;

struct thr {
    pthread_t t;
    int id;
    long rounds, bad, nivcsw, nvcsw;
    unsigned char in[MAXREGS * MAXBYTES] __attribute__((aligned(64)));
    unsigned char out[MAXREGS * MAXBYTES] __attribute__((aligned(64)));
};

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void *worker(void *arg)
{
    struct thr *t = arg;
    int bytes = width / 8;
    uint64_t x = 0x9E3779B97F4A7C15ull * (uint64_t)(t->id + 1);
    double end = now() + seconds;
    while (now() < end) {
        for (int r = 0; r < nregs; r++)
            for (int b = 0; b < bytes; b += 8) {
                x ^= x << 13; x ^= x >> 7; x ^= x << 17;  /* xorshift64 */
                uint64_t v = x | 1;  /* never all ones: the clobber value */
                memcpy(&t->in[r * MAXBYTES + b], &v, 8);
            }
        memset(t->out, 0, sizeof t->out);
        long clob = clobber && t->id == 0;
        if (width == 512)
            run_zmm(t->in, t->out, iters, spin, clob);
        else if (width == 256)
            run_ymm(t->in, t->out, iters, spin, clob);
        else
            run_xmm(t->in, t->out, iters, spin, clob);
        for (int r = 0; r < nregs; r++)
            if (memcmp(&t->in[r * MAXBYTES], &t->out[r * MAXBYTES], bytes))
                t->bad++;
        t->rounds++;
    }
    struct rusage ru;
    if (getrusage(RUSAGE_THREAD, &ru) == 0) {
        t->nivcsw = ru.ru_nivcsw;
        t->nvcsw = ru.ru_nvcsw;
    }
    return NULL;
}

int main(int argc, char **argv)
{
    int nthreads = 4, want = 0;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--seconds") && i + 1 < argc) seconds = atof(argv[++i]);
        else if (!strcmp(argv[i], "--threads") && i + 1 < argc) nthreads = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--width") && i + 1 < argc) want = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--spin") && i + 1 < argc) spin = atol(argv[++i]);
        else if (!strcmp(argv[i], "--clobber")) clobber = 1;
        else { fprintf(stderr, "vcan_regcheck: bad argument %s\n", argv[i]); return 2; }
    }
    if (nthreads < 1 || nthreads > MAXTHREADS || seconds <= 0 || spin < 1) {
        fprintf(stderr, "vcan_regcheck: bad --threads, --seconds or --spin\n");
        return 2;
    }
    __builtin_cpu_init();
    width = __builtin_cpu_supports("avx512f") ? 512 : __builtin_cpu_supports("avx") ? 256 : 128;
    if (want) {
        if (want > width || (want != 512 && want != 256 && want != 128)) {
            fprintf(stderr, "vcan_regcheck: --width %d not available (widest: %d)\n", want, width);
            return 2;
        }
        width = want;
    }
    nregs = width == 512 ? 32 : 16;
    static struct thr th[MAXTHREADS];
    for (int i = 0; i < nthreads; i++) {
        th[i].id = i;
        if (pthread_create(&th[i].t, NULL, worker, &th[i])) {
            perror("pthread_create");
            return 2;
        }
    }
    long rounds = 0, bad = 0, nivcsw = 0, nvcsw = 0, bad0 = 0, rounds0 = 0;
    for (int i = 0; i < nthreads; i++) {
        pthread_join(th[i].t, NULL);
        rounds += th[i].rounds;
        bad += th[i].bad;
        nivcsw += th[i].nivcsw;
        nvcsw += th[i].nvcsw;
    }
    bad0 = th[0].bad;
    rounds0 = th[0].rounds;
    printf("regcheck: width %d bits, %d registers, %d threads, %.1f s, %ld rounds, "
           "%ld yields, %ld involuntary and %ld voluntary context switches, "
           "thread 0: %ld rounds %ld corruptions%s, corruptions %ld\n",
           width, nregs, nthreads, seconds, rounds, rounds * iters, nivcsw, nvcsw,
           rounds0, bad0, clobber ? " (clobbering)" : "", bad);
    return bad ? 1 : 0;
}
