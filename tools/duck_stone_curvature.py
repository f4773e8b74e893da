"""duck_stone: curvature of the stone's top under the duck's lowest point, the duck's bottom, and the
rolling-stability criterion (max eigenvalue of K_duck + K_stone < 1/h). Run: PYTHONPATH=src python3 tools/duck_stone_curvature.py"""
import sys, numpy as np
from scipy.optimize import brentq
from physgs_steps.builtin_scenes import catalog as C

gt = C.build("duck_stone")
duck = gt.instances[gt.instance_names.index("duck")]
stone = gt.instances[gt.instance_names.index("stone")]
ss = stone.parts[0].solid
m = ss.mesh()
print("stone aabb", [np.round(x, 4) for x in stone.aabb()])
print("stone volume m^3 %.4e" % m.volume, " mesh area", round(m.area, 4))
body = C._part(duck, "body").solid
# duck lowest point (all parts)
A_inv = body.rot @ np.diag(body.radii**2) @ body.rot.T
dlow = body.center - A_inv[:, 2] / np.sqrt(A_inv[2, 2])  # the (tilted) body's support point in -z
# duck com (union approx: sample inside)
lo, hi = duck.aabb(); rng = np.random.default_rng(0)
P = rng.uniform(lo, hi, (400000, 3)); ins = np.zeros(len(P), bool)
for p in duck.parts: ins |= p.solid.inside(P)
dcom = P[ins].mean(0)
print("duck com - lowest point (x, y) mm", ((dcom - dlow)[:2] * 1000).round(2))
print("duck lowest", dlow.round(4), "duck com", dcom.round(4), "com height above bottom %.4f" % (dcom[2]-dlow[2]))
sv = ss.to_world(np.asarray(m.vertices)); scom = ss.to_world(np.asarray(m.center_mass)[None])[0]
print("stone com", scom.round(4), "stone top z %.4f" % sv[:, 2].max(), "lowest", sv[sv[:,2].argmin()].round(4))

def top(x, y):
    f = lambda z: float(ss.local_implicit(ss.to_local(np.array([[x, y, z]])))[0])
    zhi = sv[:, 2].max() + 0.01
    zlo = scom[2]
    if f(zlo) > 0: return np.nan
    return brentq(f, zlo, zhi, xtol=1e-9)

def fit(x0, y0, s=0.02, n=9):
    g = np.linspace(-s, s, n); X, Y = np.meshgrid(g, g); X, Y = X.ravel(), Y.ravel()
    Z = np.array([top(x0 + a, y0 + b) for a, b in zip(X, Y)])
    A = np.stack([np.ones_like(X), X, Y, X*X, X*Y, Y*Y], 1)
    c = np.linalg.lstsq(A, Z, rcond=None)[0]
    H = np.array([[2*c[3], c[4]], [c[4], 2*c[5]]]); gr = c[1:3]
    slope = np.degrees(np.arctan(np.linalg.norm(gr)))
    # curvature of graph: approx H/(1+|g|^2)^(3/2) for small slopes
    k = H / (1 + gr @ gr) ** 1.5
    return k, slope, gr

for s in (0.015, 0.025):
    k, slope, gr = fit(dlow[0], dlow[1], s)
    kx, ky = -k[0, 0], -k[1, 1]
    w, V = np.linalg.eigh(-k)
    print(f"under duck (x={dlow[0]:.4f}, y={dlow[1]:.4f}) patch +-{s}: slope {slope:.2f} deg; R along(x) {1/kx:.3f} m, across(y) {1/ky:.3f} m; principal R {1/w[0]:.3f},{1/w[1]:.3f} dirs {V[:,0].round(2)}")
# duck bottom curvature: body ellipsoid bottom: radii a^2/c
def bottom_k(solid, x0, y0, s=0.006, n=9):
    g = np.linspace(-s, s, n); X, Y = np.meshgrid(g, g); X, Y = X.ravel(), Y.ravel()
    f = lambda x, y, z: float(solid.sdf(np.array([[x, y, z]]))[0])
    Z = np.array([brentq(lambda z: f(x0 + a, y0 + b, z), dlow[2] - 0.01, solid.center[2], xtol=1e-10) for a, b in zip(X, Y)])
    c = np.linalg.lstsq(np.stack([np.ones_like(X), X, Y, X*X, X*Y, Y*Y], 1), Z, rcond=None)[0]
    return np.array([[2*c[3], c[4]], [c[4], 2*c[5]]])
Kd = bottom_k(body, dlow[0], dlow[1])
rd_along, rd_across = 1 / Kd[0, 0], 1 / Kd[1, 1]
h = dcom[2] - dlow[2]
print(f"duck bottom R along {rd_along:.3f} across {rd_across:.3f}, h {h:.4f}")
k, slope, gr = fit(dlow[0], dlow[1], 0.02)
Rx, Ry = 1/ -k[0,0], 1/ -k[1,1]
for nm, rd, R in (("across", rd_across, Ry), ("along", rd_along, Rx)):
    need = 1/(1/h - 1/rd)
    print(f"{nm}: 1/h={1/h:.2f} vs 1/r+1/R={1/rd + 1/R:.2f}; needs R>{need:.3f}, has {R:.3f} (x{R/need:.2f})")
Ks = -k
ev = np.linalg.eigvalsh(Kd + Ks)
print(f"3D: max eig(K_duck+K_stone) {ev.max():.2f} /m vs 1/h {1/h:.2f}: margin h*lam = {h*ev.max():.3f} (<1 stable); stone principal R {1/np.linalg.eigvalsh(Ks)[::-1].round(3)}")
