# Pure-Python XXH3-64 (seed 0, default secret), ported from xxhash-rust's const_xxh3.rs.
M = (1 << 64) - 1
SECRET = bytes.fromhex(
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671f"
    "cb79e64eccc0e578825ad07dccff7221b8084674f743248ee03590e6813a264c"
    "3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364"
    "eac5ac8334d3ebc3c581a0fffa1363eb170ddd51b7f0da49d316552629d4689e"
    "2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e")
P64_1, P64_2, P64_3, P64_4, P64_5 = (0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9,
                                     0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5)
P32_1, P32_2, P32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D

def _r64(b, o): return int.from_bytes(b[o:o + 8], "little")
def _r32(b, o): return int.from_bytes(b[o:o + 4], "little")
def _fold(a, b):
    p = a * b
    return (p & M) ^ (p >> 64)
def _av(h):
    h ^= h >> 37; h = (h * 0x165667919E3779F9) & M; return h ^ (h >> 32)
def _av64(h):
    h ^= h >> 33; h = (h * P64_2) & M; h ^= h >> 29; h = (h * P64_3) & M; return h ^ (h >> 32)
def _rotl(x, r): return ((x << r) | (x >> (64 - r))) & M
def _strong(h, n):
    h ^= _rotl(h, 49) ^ _rotl(h, 24); h = (h * 0x9FB21C651E98DF25) & M
    h ^= (h >> 35) + n; h &= M; h = (h * 0x9FB21C651E98DF25) & M; return h ^ (h >> 28)
def _mix16(b, o, so):
    return _fold(_r64(b, o) ^ _r64(SECRET, so), _r64(b, o + 8) ^ _r64(SECRET, so + 8))
def _bswap64(x): return int.from_bytes(x.to_bytes(8, "little"), "big")

def xxh3_64(b: bytes) -> int:
    n = len(b); s = SECRET
    if n == 0:
        return _av64(_r64(s, 56) ^ _r64(s, 64))
    if n <= 3:
        combo = (b[0] << 16) | (b[n >> 1] << 24) | b[n - 1] | (n << 8)
        return _av64(combo ^ (_r32(s, 0) ^ _r32(s, 4)))
    if n <= 8:
        i1, i2 = _r32(b, 0), _r32(b, n - 4)
        flip = _r64(s, 8) ^ _r64(s, 16)
        return _strong(((i2 + (i1 << 32)) & M) ^ flip, n)
    if n <= 16:
        lo = _r64(b, 0) ^ (_r64(s, 24) ^ _r64(s, 32))
        hi = _r64(b, n - 8) ^ (_r64(s, 40) ^ _r64(s, 48))
        return _av((n + _bswap64(lo) + hi + _fold(lo, hi)) & M)
    if n <= 128:
        acc = (n * P64_1) & M
        if n > 32:
            if n > 64:
                if n > 96:
                    acc += _mix16(b, 48, 96) + _mix16(b, n - 64, 112)
                acc += _mix16(b, 32, 64) + _mix16(b, n - 48, 80)
            acc += _mix16(b, 16, 32) + _mix16(b, n - 32, 48)
        acc += _mix16(b, 0, 0) + _mix16(b, n - 16, 16)
        return _av(acc & M)
    if n <= 240:
        acc = (n * P64_1) & M
        for i in range(8):
            acc = (acc + _mix16(b, 16 * i, 16 * i)) & M
        acc = _av(acc)
        for i in range(8, n // 16):
            acc = (acc + _mix16(b, 16 * i, 16 * (i - 8) + 3)) & M
        acc = (acc + _mix16(b, n - 16, 136 - 17)) & M
        return _av(acc)
    acc = [P32_3, P64_1, P64_2, P64_3, P64_4, P32_2, P64_5, P32_1]
    skeys = [[_r64(s, so + 8 * i) for i in range(8)] for so in range(0, 193, 8) if so + 64 <= 192]
    def accum(o, so_keys):
        for i in range(8):
            v = _r64(b, o + 8 * i); k = v ^ so_keys[i]
            acc[i ^ 1] = (acc[i ^ 1] + v) & M
            acc[i] = (acc[i] + (k & 0xFFFFFFFF) * (k >> 32)) & M
    nstripes = (192 - 64) // 8; block = 64 * nstripes
    nblocks = (n - 1) // block
    scr = [_r64(s, 192 - 64 + 8 * i) for i in range(8)]
    for blk in range(nblocks):
        for st in range(nstripes):
            accum(blk * block + st * 64, skeys[st])
        for i in range(8):
            a = acc[i] ^ (acc[i] >> 47); a ^= scr[i]; acc[i] = (a * P32_1) & M
    ns = ((n - 1) - block * nblocks) // 64
    for st in range(ns):
        accum(nblocks * block + st * 64, skeys[st])
    accum(n - 64, [_r64(s, 192 - 64 - 7 + 8 * i) for i in range(8)])
    res = (n * P64_1) & M
    for i in range(4):
        res = (res + _fold(acc[2 * i] ^ _r64(s, 11 + 16 * i), acc[2 * i + 1] ^ _r64(s, 11 + 16 * i + 8))) & M
    return _av(res)
