/* uml-xsave-shim.c: an LD_PRELOAD library for Debian's User-Mode Linux (linux.uml) on
 * hosts whose XSAVE area is larger than the one UML was built for (AMX: 11008 bytes).
 *
 * The ptrace contract it works around (host kernel, arch/x86/kernel/fpu/regset.c and
 * kernel/ptrace.c ptrace_regset()):
 *   * PTRACE_GETREGSET(NT_X86_XSTATE) with an iovec shorter than the host's XSAVE size
 *     (fpu_user_cfg.max_size) is merely truncated: the first iov_len bytes come back.
 *   * PTRACE_SETREGSET(NT_X86_XSTATE) must be given *exactly* the host's size: a shorter
 *     iovec fails with EFAULT (xstateregs_set: "count != fpu_user_cfg.max_size"); a longer
 *     one is clamped to the host's size first, so it works.
 * UML saves and restores every guest task's FP state with these calls, using a buffer of
 * a size fixed when UML was compiled (2696 bytes in Debian's 6.1: x87, SSE, AVX, AVX-512,
 * PKRU). On an AMX host (TILECFG at 2752, 8 KiB TILEDATA at 2816) the very first
 * SETREGSET fails and UML panics: "userspace - ptrace set fp regs failed, errno = 14".
 *
 * What the shim does: it wraps ptrace(). A PTRACE_SETREGSET(NT_X86_XSTATE) whose iov_len
 * is shorter than the host's XSAVE size is re-issued at the host's size: UML's bytes, then
 * zeros, and XSTATE_BV in the XSAVE header (offset 512) limited to the state components
 * that lie wholly inside UML's buffer (offsets and sizes from CPUID leaf 0xD, the standard
 * format that ptrace uses). The components beyond (AMX) are thereby put in their initial
 * state; a UML guest can never be granted AMX (arch_prctl(ARCH_REQ_XCOMP_PERM) is the
 * host's, and UML does not forward it), so nothing is lost. XCOMP_BV (offset 520) is
 * copied from UML's bytes unchanged (ptrace's format is the standard one: it is 0).
 * Every other call passes through untouched, and so does this one when UML's buffer is
 * at least the host's size: on such a host the shim changes nothing.
 *
 * The host's layout is read once, when the library is loaded (CPUID per call made UML's
 * boot ten times slower). Built by scripts/vcan-run as a shared library; the padding is
 * xsave_pad(), exported for tests/test_xsave_shim.py (with xsave_host_size() and, for the
 * test only, xsave_xcr0() and xsave_layout_end()). With UML_XSAVE_SHIM_REPORT=FILE it
 * also appends one line per NT_X86_XSTATE call to FILE ("get|set IOV_LEN HOST_SIZE"),
 * which vcan-run uses once to learn UML's buffer size (a trial boot). For testing on a host
 * that does not need it, UML_XSAVE_SHIM_PAD_TO=N (N >= the host's size) pads every short
 * SETREGSET to N bytes instead: the host kernel clamps a longer iovec to its own size, so
 * the padding path runs for real (vcan-run's VCAN_RUN_XSAVE_SHIM=pad-test).
 */
#define _GNU_SOURCE
#include <cpuid.h>
#include <dlfcn.h>
#include <elf.h>
#include <errno.h>
#include <fcntl.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/types.h>
#include <sys/uio.h>
#include <unistd.h>

#ifndef NT_X86_XSTATE
#define NT_X86_XSTATE 0x202
#endif

#define XSAVE_HDR_OFFSET 512
#define XSAVE_HDR_SIZE 64
#define XSAVE_MAX_COMPONENTS 64
#define XSAVE_BUF_MAX (64 * 1024)

/* Pad a short XSAVE image for PTRACE_SETREGSET.
 *   src, src_len: UML's buffer; dst, dst_len: the host's size.
 *   offsets[i], sizes[i] (i < n): state component i in the standard format (CPUID 0xD
 *   sub-leaf i: EBX, EAX); size 0 = not a user component here. Components 0 (x87) and
 *   1 (SSE) live in the legacy area and the header, so they fit once the header does.
 * Returns 1 when src_len >= dst_len (nothing to do: pass the call through as it is),
 * 0 when dst has been filled, -1 when src is too short to hold the XSAVE header. */
int xsave_pad(const void *src, size_t src_len, void *dst, size_t dst_len,
              const uint32_t *offsets, const uint32_t *sizes, unsigned n)
{
    if (src_len >= dst_len)
        return 1;
    if (src_len < XSAVE_HDR_OFFSET + XSAVE_HDR_SIZE)
        return -1;
    memcpy(dst, src, src_len);
    memset((char *)dst + src_len, 0, dst_len - src_len);
    uint64_t fits = 0x3;  /* x87, SSE */
    for (unsigned i = 2; i < n && i < XSAVE_MAX_COMPONENTS; i++)
        if (sizes[i] && (uint64_t)offsets[i] + sizes[i] <= src_len)
            fits |= (uint64_t)1 << i;
    uint64_t bv;
    memcpy(&bv, (char *)dst + XSAVE_HDR_OFFSET, sizeof bv);
    bv &= fits;
    memcpy((char *)dst + XSAVE_HDR_OFFSET, &bv, sizeof bv);
    return 0;
}

/* The host's XSAVE layout, read once. */
static uint32_t host_size;
static uint32_t comp_off[XSAVE_MAX_COMPONENTS], comp_size[XSAVE_MAX_COMPONENTS];

/* CPUID.(EAX=0xD,ECX=0): EBX = size for the features enabled in XCR0 (AMX included where
 * the host kernel enables it), EAX:EDX = the user components XCR0 may hold. */
uint32_t xsave_host_size(void)
{
    unsigned a, b, c, d;
    if (__get_cpuid_max(0, NULL) < 0xD)
        return 0;
    __cpuid_count(0xD, 0, a, b, c, d);
    return b;
}

/* XCR0, the state components the OS has enabled, read with XGETBV (ECX = 0); 0 where the
 * OS has not enabled XSAVE (CPUID.1:ECX.OSXSAVE clear: XGETBV would fault). */
uint64_t xsave_xcr0(void)
{
    unsigned a, b, c, d, lo, hi;
    if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & bit_OSXSAVE))
        return 0;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    return ((uint64_t)hi << 32) | lo;
}

/* The end of the host's XSAVE image in the standard format, worked out from the layout
 * rather than taken from CPUID.(EAX=0xD,ECX=0).EBX: the largest offset + size (CPUID 0xD
 * sub-leaf i: EBX, EAX) over the user state components i >= 2 enabled in XCR0 (XGETBV),
 * and at least the legacy area and the XSAVE header (x87 and SSE live there: 576 bytes).
 * Not used by the shim; tests/test_xsave_shim.py checks xsave_host_size() against it on
 * whatever host it runs. 0 without XSAVE enabled by the OS. */
uint32_t xsave_layout_end(void)
{
    unsigned a, b, c, d;
    if (__get_cpuid_max(0, NULL) < 0xD)
        return 0;
    uint64_t xcr0 = xsave_xcr0();
    if (!xcr0)
        return 0;
    uint32_t end = XSAVE_HDR_OFFSET + XSAVE_HDR_SIZE;
    for (unsigned i = 2; i < XSAVE_MAX_COMPONENTS; i++) {
        if (!(xcr0 & ((uint64_t)1 << i)))
            continue;
        __cpuid_count(0xD, i, a, b, c, d);
        if (c & 1)  /* supervisor state (never in XCR0, but as read_layout does) */
            continue;
        if (a && b + a > end)
            end = b + a;
    }
    return end;
}

static void read_layout(void)
{
    unsigned a, b, c, d, xcr0_lo, xcr0_hi;
    host_size = xsave_host_size();
    if (!host_size)
        return;
    __cpuid_count(0xD, 0, xcr0_lo, b, c, xcr0_hi);
    uint64_t user = ((uint64_t)xcr0_hi << 32) | xcr0_lo;
    for (unsigned i = 2; i < XSAVE_MAX_COMPONENTS; i++) {
        if (!(user & ((uint64_t)1 << i)))
            continue;
        __cpuid_count(0xD, i, a, b, c, d);
        if (c & 1)  /* supervisor state: not in a user XSAVE image */
            continue;
        comp_size[i] = a;
        comp_off[i] = b;
    }
}

typedef long (*ptrace_fn)(int, pid_t, void *, void *);
static ptrace_fn real_ptrace;
static const char *report_path;

__attribute__((constructor)) static void shim_init(void)
{
    read_layout();
    real_ptrace = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");
    report_path = getenv("UML_XSAVE_SHIM_REPORT");
    const char *pad_to = getenv("UML_XSAVE_SHIM_PAD_TO");
    if (pad_to && host_size) {
        unsigned long n = strtoul(pad_to, NULL, 10);
        if (n >= host_size && n <= XSAVE_BUF_MAX)
            host_size = (uint32_t)n;
    }
}

static void report(const char *what, size_t len)
{
    char line[96];
    int n = snprintf(line, sizeof line, "%s %zu %u\n", what, len, host_size);
    int fd = open(report_path, O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0644);
    if (fd >= 0) {
        if (write(fd, line, n) < 0) { /* nothing to do */ }
        close(fd);
    }
}

long ptrace(enum __ptrace_request request, ...)
{
    va_list ap;
    va_start(ap, request);
    pid_t pid = va_arg(ap, pid_t);
    void *addr = va_arg(ap, void *);
    void *data = va_arg(ap, void *);
    va_end(ap);
    if (!real_ptrace) {
        errno = ENOSYS;
        return -1;
    }
    if ((request == PTRACE_SETREGSET || request == PTRACE_GETREGSET) &&
        (uintptr_t)addr == NT_X86_XSTATE && data) {
        struct iovec *iov = data;
        if (report_path)
            report(request == PTRACE_SETREGSET ? "set" : "get", iov->iov_len);
        if (request == PTRACE_SETREGSET && iov->iov_len < host_size &&
            host_size <= XSAVE_BUF_MAX) {
            /* UML's tracer is single-threaded per host process: a static buffer will do. */
            static unsigned char buf[XSAVE_BUF_MAX] __attribute__((aligned(64)));
            if (xsave_pad(iov->iov_base, iov->iov_len, buf, host_size, comp_off, comp_size,
                          XSAVE_MAX_COMPONENTS) == 0) {
                struct iovec big = { buf, host_size };
                return real_ptrace(request, pid, addr, &big);
            }
        }
    }
    return real_ptrace(request, pid, addr, data);
}
