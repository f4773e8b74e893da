"""Staged stores: G2P's new particle state written through shared memory (CUDA).

The per-particle arrays are ``ti.ndarray``s of vectors and matrices, stored particle by
particle (x[p] is 3 floats in a row, F[p] 9).  A thread that stores its particle's F issues 9
scalar stores; across a warp each of them touches 32 addresses 36 bytes apart, so every
instruction writes a 4-byte piece of 36 different 32-byte sectors, and L2 merges those partial
writes.  G2P writes x, v, C, F and tau (33 floats a particle): about 33 sector writes a
particle where 4.1 would carry the bytes.  Nsight Compute on the landed jelly box of
bench_mpm.py at 10^6 particles (one H100, 2026-11-28): G2P 327 us, its L2 at 84.5 % of its
throughput (the kernel's limit), 29.3 M sector writes a launch (docs/MEASURED.md "Issue 18, tenth
round").

So G2P stages: each thread puts its particle's 33 new values into shared memory
(:func:`stage_put`, a block of :data:`STAGE_BLOCK` threads and particles), the block
synchronises, then the block's threads store the block's contiguous range of each array word
by word (:func:`stage_write`): consecutive threads, consecutive words, whole sectors.  Same
values, same arrays; only the order of the stores differs.  CUDA only (Taichi's shared arrays
and block barrier exist there alone), without rigid bodies (their particles' F and tau are
set by rigid.py, not stored here): ``kernels.Spec.staged``, which ``MPMSolver(staged=None)``
turns on there.

The loads were staged the same way and dropped: warp-run P2G's x, v, C and tau, and G2P's x
and F, read word by word into shared memory before the particle's work.  On one H200 (bench_mpm.py,
10^6 particles, same call) stores alone ran 1.86e9 particle-substeps/s, stores and P2G's loads
1.68e9, stores and G2P's loads 1.42e9, all three 1.25e9, none 1.59e9: the loads hit L1 (a
warp's 9 loads of a matrix share 36 sectors), and staging them added barriers and registers
(G2P 220 registers a thread, P2G 400 us against 313 us).
"""

import taichi as ti

STAGE_BLOCK = 128  # threads a block, particles staged together
# shared-memory words a particle: x 3, v 3, C 9, F 9, tau 9
X0, V0, C0, F0, T0 = 0, 3, 6, 15, 24
STAGE_WORDS = 33


@ti.func
def stage_put(sh: ti.template(), tid, x_new, v_new, C_new, F_new, tau_new):
    """Thread ``tid``'s particle's new state into the block's shared array ``sh``
    [STAGE_BLOCK * STAGE_WORDS]: each array's block of words in particle order (x at
    X0 * STAGE_BLOCK + 3 tid + a, and so on), as the arrays hold them."""
    for a in ti.static(range(3)):
        sh[X0 * STAGE_BLOCK + 3 * tid + a] = x_new[a]
        sh[V0 * STAGE_BLOCK + 3 * tid + a] = v_new[a]
    for a, b in ti.static(ti.ndrange(3, 3)):
        sh[C0 * STAGE_BLOCK + 9 * tid + 3 * a + b] = C_new[a, b]
        sh[F0 * STAGE_BLOCK + 9 * tid + 3 * a + b] = F_new[a, b]
        sh[T0 * STAGE_BLOCK + 9 * tid + 3 * a + b] = tau_new[a, b]


@ti.func
def _write_vec(sh: ti.template(), w0: ti.template(), tid, p0, P, a: ti.template()):
    for r in ti.static(range(3)):  # the block's 3 STAGE_BLOCK words of a, STAGE_BLOCK at a time
        w = tid + r * STAGE_BLOCK
        q = p0 + w // 3
        if q < P:
            a[q][w % 3] = sh[w0 * STAGE_BLOCK + w]


@ti.func
def _write_mat(sh: ti.template(), w0: ti.template(), tid, p0, P, a: ti.template()):
    for r in ti.static(range(9)):
        w = tid + r * STAGE_BLOCK
        q = p0 + w // 9
        c = w % 9
        if q < P:
            a[q][c // 3, c % 3] = sh[w0 * STAGE_BLOCK + w]


@ti.func
def stage_write(sh: ti.template(), tid, p0, P, x: ti.template(), v: ti.template(), C: ti.template(),
                F: ti.template(), tau: ti.template()):
    """The block's staged state (particles p0 .. p0 + STAGE_BLOCK - 1, those below P) into the
    arrays, thread ``tid`` storing words tid, tid + STAGE_BLOCK, ...  of each.  Call it after
    the block's barrier, from every thread of the block."""
    _write_vec(sh, X0, tid, p0, P, x)
    _write_vec(sh, V0, tid, p0, P, v)
    _write_mat(sh, C0, tid, p0, P, C)
    _write_mat(sh, F0, tid, p0, P, F)
    _write_mat(sh, T0, tid, p0, P, tau)

