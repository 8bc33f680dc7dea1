"""The padding of scripts/uml-xsave-shim.c (the LD_PRELOAD library that lets Debian's UML
boot where the host's XSAVE area is larger than UML's buffer, e.g. with AMX).

The shim is compiled here with gcc (scripts/bootstrap --test installs it) and its exported
``xsave_pad`` is called through ctypes with synthetic hosts (the layouts of CPUID leaf 0xD:
an AMX host, 11008 bytes; Intel's AVX-512 layout, 2688; AMD Zen 4's, 2432) and UML's buffer
of 2696 bytes (Debian's 6.1) or shorter ones. Nothing here assumes what this host is: its
XSAVE size is checked against the layout the same CPU reports (XCR0 and CPUID 0xD's
sub-leaves), and the shim's ptrace() wrapper against a real traced child (a SETREGSET
shorter than the host's size: EFAULT plain, accepted through the shim). Under UML the shim
is exercised in the vcan suite (``VCAN_RUN_XSAVE_SHIM=always`` / ``pad-test``, see
scripts/vcan-run).
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import signal
import struct
import subprocess
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "scripts" / "uml-xsave-shim.c"
HDR = 512  # the XSAVE header: XSTATE_BV at 512, XCOMP_BV at 520
NCOMP = 64

#: A host with AVX-512, PKRU and AMX (CPUID 0xD sub-leaves: component -> (offset, size)).
AMX_HOST = {2: (576, 256), 5: (1088, 64), 6: (1152, 512), 7: (1664, 1024), 9: (2688, 8),
            17: (2752, 64), 18: (2816, 8192)}
AMX_HOST_SIZE = 11008
#: Intel's AVX-512 layout without PKRU: AVX, then (after MPX's 960..1088, not enabled) opmask,
#: ZMM_Hi256, Hi16_ZMM.
INTEL_AVX512_HOST = {2: (576, 256), 5: (1088, 64), 6: (1152, 512), 7: (1664, 1024)}
INTEL_AVX512_HOST_SIZE = 2688
#: AMD Zen 4 (EPYC) without PKRU: the AVX-512 components right after AVX, no MPX gap.
AMD_ZEN4_HOST = {2: (576, 256), 5: (832, 64), 6: (896, 512), 7: (1408, 1024)}
AMD_ZEN4_HOST_SIZE = 2432
#: name -> (layout, XSAVE size): the synthetic hosts the padding is checked against
HOSTS = {"amx": (AMX_HOST, AMX_HOST_SIZE),
         "intel-avx512": (INTEL_AVX512_HOST, INTEL_AVX512_HOST_SIZE),
         "amd-zen4": (AMD_ZEN4_HOST, AMD_ZEN4_HOST_SIZE)}
UML_SIZE = 2696
#: x87, SSE, AVX, opmask, ZMM_Hi256, Hi16_ZMM, PKRU, TILECFG, TILEDATA
ALL_BV = sum(1 << i for i in (0, 1, *AMX_HOST))
AMX_BV = (1 << 17) | (1 << 18)


@pytest.fixture(scope="module")
def shim(tmp_path_factory):
    gcc = shutil.which("gcc")
    assert gcc, "gcc not found: scripts/bootstrap --test installs it (gcc, libc6-dev)"
    so = tmp_path_factory.mktemp("shim") / "uml-xsave-shim.so"
    cmd = [gcc, "-O2", "-Wall", "-Werror", "-shared", "-fPIC", "-o", str(so), str(SRC), "-ldl"]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    lib = ctypes.CDLL(str(so))
    lib.xsave_pad.restype = ctypes.c_int
    lib.xsave_pad.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_size_t,
                              ctypes.POINTER(ctypes.c_uint32), ctypes.POINTER(ctypes.c_uint32),
                              ctypes.c_uint]
    lib.xsave_host_size.restype = ctypes.c_uint32
    lib.xsave_layout_end.restype = ctypes.c_uint32
    lib.xsave_xcr0.restype = ctypes.c_uint64
    return lib


def _bv(host: dict[int, tuple[int, int]]) -> int:
    """XSTATE_BV with every component of ``host`` in use (x87 and SSE too)."""
    return sum(1 << i for i in (0, 1, *host))


def _layout_end(host: dict[int, tuple[int, int]]) -> int:
    """What xsave_layout_end() computes, for a synthetic host."""
    return max([HDR + 64, *(off + size for off, size in host.values())])


def _layout(host: dict[int, tuple[int, int]]):
    offs, sizes = (ctypes.c_uint32 * NCOMP)(), (ctypes.c_uint32 * NCOMP)()
    for i, (off, size) in host.items():
        offs[i], sizes[i] = off, size
    return offs, sizes


def _uml_image(size: int, xstate_bv: int) -> bytearray:
    """What UML's truncated GETREGSET left in its buffer: data everywhere, a header with
    ``xstate_bv`` and XCOMP_BV = 0 (ptrace's standard format)."""
    img = bytearray(os.urandom(size))
    img[HDR:HDR + 64] = struct.pack("<QQ48x", xstate_bv, 0)
    return img[:size]


def _pad(lib, src: bytes, dst_len: int, host=AMX_HOST, fill: int = 0xEE):
    offs, sizes = _layout(host)
    s = (ctypes.c_ubyte * len(src)).from_buffer_copy(src)
    d = (ctypes.c_ubyte * dst_len)(*([fill] * dst_len))
    rc = lib.xsave_pad(s, len(src), d, dst_len, offs, sizes, NCOMP)
    return rc, bytes(d)


def test_short_buffer_is_padded_to_the_host_size(shim):
    src = _uml_image(UML_SIZE, ALL_BV)
    rc, dst = _pad(shim, src, AMX_HOST_SIZE)
    assert rc == 0
    assert len(dst) == AMX_HOST_SIZE
    xstate_bv, xcomp_bv = struct.unpack_from("<QQ", dst, HDR)
    # Every component inside UML's 2696 bytes keeps its bit; AMX (at 2752 and 2816) is reset.
    assert xstate_bv == ALL_BV & ~AMX_BV == 0x2E7
    assert xcomp_bv == 0
    # UML's bytes, except XSTATE_BV; zeros beyond (the initial state of the rest).
    assert dst[:HDR] == src[:HDR]
    assert dst[HDR + 8:UML_SIZE] == src[HDR + 8:UML_SIZE]
    assert dst[UML_SIZE:] == bytes(AMX_HOST_SIZE - UML_SIZE)


def test_components_cut_by_the_buffer_end_are_reset(shim):
    """A component only partly inside UML's buffer is not taken from it either."""
    src = _uml_image(2000, ALL_BV)  # Hi16_ZMM (1664 + 1024) and PKRU (2688) do not fit
    rc, dst = _pad(shim, src, AMX_HOST_SIZE)
    assert rc == 0
    assert struct.unpack_from("<Q", dst, HDR)[0] == sum(1 << i for i in (0, 1, 2, 5, 6))
    assert dst[2000:] == bytes(AMX_HOST_SIZE - 2000)


def test_bits_not_set_stay_clear_and_unknown_components_are_dropped(shim):
    # Only x87 | SSE | AVX in use, plus a bit the host does not have (component 40).
    src = _uml_image(UML_SIZE, 0x7 | (1 << 40))
    rc, dst = _pad(shim, src, AMX_HOST_SIZE)
    assert rc == 0
    assert struct.unpack_from("<Q", dst, HDR)[0] == 0x7


@pytest.mark.parametrize("src_len, dst_len", [(2696, 2696), (2696, 2440), (11008, 11008)])
def test_pass_through_when_uml_buffer_is_large_enough(shim, src_len, dst_len):
    """Sizes equal, or UML's larger (the host kernel clamps a long iovec): nothing to do."""
    rc, dst = _pad(shim, _uml_image(src_len, ALL_BV), dst_len)
    assert rc == 1
    assert dst == bytes([0xEE]) * dst_len  # not written


def test_too_short_for_the_header_is_refused(shim):
    rc, dst = _pad(shim, _uml_image(HDR + 63, 0x3), AMX_HOST_SIZE)
    assert rc == -1
    assert dst == bytes([0xEE]) * AMX_HOST_SIZE


@pytest.mark.parametrize("name", list(HOSTS))
def test_synthetic_hosts_size_is_their_layout_end(name):
    """The sizes the padding tests use are their layouts' ends (as xsave_layout_end()
    computes it for a real host): Intel's AVX-512 and AMD's differ by MPX's gap."""
    host, size = HOSTS[name]
    assert _layout_end(host) == size


@pytest.mark.parametrize("src_len", [HDR + 64, 832, 1500, 2000, 2432, 2440, 2688, 2696])
@pytest.mark.parametrize("name", list(HOSTS))
def test_padding_for_each_host_layout(shim, name, src_len):
    """For each layout, a buffer shorter than the host's size is padded to it; the
    components wholly inside the buffer keep their XSTATE_BV bits, the others are reset
    (zeros, bit clear); a buffer at least the host's size passes through untouched."""
    host, size = HOSTS[name]
    src = _uml_image(src_len, _bv(host))
    rc, dst = _pad(shim, src, size, host)
    if src_len >= size:
        assert rc == 1
        assert dst == bytes([0xEE]) * size
        return
    assert rc == 0
    fits = [0, 1] + [i for i, (off, n) in host.items() if off + n <= src_len]
    assert struct.unpack_from("<QQ", dst, HDR) == (sum(1 << i for i in fits), 0)
    assert dst[:HDR] == src[:HDR]
    assert dst[HDR + 8:src_len] == src[HDR + 8:]
    assert dst[src_len:] == bytes(size - src_len)


def test_host_size_is_cpuid_0xd(shim):
    """The host's XSAVE size as the shim reads it (CPUID 0xD sub-leaf 0, EBX) is the end of
    the layout the same CPU describes component by component (sub-leaves i: offset, size)
    for the components the OS enabled in XCR0 (XGETBV), whatever the vendor: Intel's
    AVX-512 ends at 2688 (after MPX's area), AMD Zen 4's at 2432, AMX's at 11008. At least
    the legacy area and the header, and AVX's end where XCR0 enables AVX."""
    xcr0 = shim.xsave_xcr0()
    if not xcr0:  # the OS has not enabled XSAVE (CPUID.1:ECX.OSXSAVE clear): no components
        assert shim.xsave_layout_end() == HDR + 64
        return
    size = shim.xsave_host_size()
    assert xcr0 & 0x3 == 0x3, f"XCR0 {xcr0:#x}: x87 and SSE are always enabled"
    assert size == shim.xsave_layout_end(), f"XCR0 {xcr0:#x}"
    assert size >= HDR + 64
    if xcr0 & 0x4:  # AVX: YMM_Hi128 at 576..832 in every layout
        assert size >= 832


# ---------------------------------------------------------------- the ptrace contract, here
PTRACE_TRACEME, PTRACE_GETREGSET, PTRACE_SETREGSET = 0, 0x4204, 0x4205
NT_X86_XSTATE = 0x202
XMM0 = 160  # offset of xmm0 in the legacy (FXSAVE) area


class _Iovec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


def _ptrace_fn(lib):
    f = lib.ptrace
    f.restype = ctypes.c_long
    f.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
    return f


def test_shim_reissues_a_short_setregset_at_the_host_size(shim):
    """On this host, against a real traced child: the kernel refuses a PTRACE_SETREGSET
    (NT_X86_XSTATE) shorter than its XSAVE size (EFAULT) — what makes UML panic on an AMX
    host — and the same call through the shim's ptrace() succeeds, the registers in it
    arrive, and components beyond the short buffer are reset (XSTATE_BV masked)."""
    host = shim.xsave_host_size()
    assert host > HDR + 64, f"host XSAVE size {host}: no room for a shorter image"
    # legacy area, header and AVX (PKRU, AVX-512, AMX beyond); without AVX, no AVX
    avx = bool(shim.xsave_xcr0() & 0x4)
    short, kept = (832, 0x7) if avx and host > 832 else (HDR + 64, 0x3)
    libc = ctypes.CDLL(None, use_errno=True)
    plain, wrapped = _ptrace_fn(libc), _ptrace_fn(shim)
    pid = os.fork()
    if pid == 0:  # the tracee: stop and wait to be killed
        try:
            plain(PTRACE_TRACEME, 0, None, None)
            os.kill(os.getpid(), signal.SIGSTOP)
        finally:
            os._exit(0)
    try:
        _, status = os.waitpid(pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), status
        full = (ctypes.c_ubyte * (host + 4096))()
        iov = _Iovec(ctypes.addressof(full), len(full))
        assert plain(PTRACE_GETREGSET, pid, NT_X86_XSTATE, ctypes.byref(iov)) == 0
        assert iov.iov_len == host  # the kernel's size is CPUID 0xD's
        img = (ctypes.c_ubyte * short).from_buffer_copy(bytes(full)[:short])
        marker = bytes(range(0x40, 0x50))
        img[XMM0:XMM0 + 16] = list(marker)
        bv = struct.unpack_from("<Q", bytes(img), HDR)[0] | kept  # x87, SSE (AVX) in use
        struct.pack_into("<Q", img, HDR, bv)
        iov = _Iovec(ctypes.addressof(img), short)
        assert plain(PTRACE_SETREGSET, pid, NT_X86_XSTATE, ctypes.byref(iov)) == -1
        assert ctypes.get_errno() == errno.EFAULT
        iov = _Iovec(ctypes.addressof(img), short)
        assert wrapped(PTRACE_SETREGSET, pid, NT_X86_XSTATE, ctypes.byref(iov)) == 0
        iov = _Iovec(ctypes.addressof(full), len(full))
        assert plain(PTRACE_GETREGSET, pid, NT_X86_XSTATE, ctypes.byref(iov)) == 0
        back = bytes(full)[:host]
        assert back[XMM0:XMM0 + 16] == marker
        assert struct.unpack_from("<Q", back, HDR)[0] & ~kept == 0  # nothing beyond
        # A full-size call passes through the shim unchanged.
        iov = _Iovec(ctypes.addressof(full), host)
        assert wrapped(PTRACE_SETREGSET, pid, NT_X86_XSTATE, ctypes.byref(iov)) == 0
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
