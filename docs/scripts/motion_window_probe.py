"""How much of the history scene's true skirt state each motion-context window holds.

A linear probe, not a network: ridge regression (10 contiguous folds of frames, the best of
five ridge weights) of the ingest entry's `garment_state` (hem deflection, twist and their
rates, in the body's heading frame) on window features built as the motion context samples
them (for scale s and l in 0..L: the hip band's displacement between frames max(t - l s, 0)
and max(t - (l + 1) s, 0) divided by s, and the root's rotation delta), in world space (the
paper's), in the body frame of the query frame t, or in the body frame of each sampled frame
u. R2 is over the history frames. Needs `pip install zarr numpy` and a cache holding the
history scene's ingest and motion entries:

    pipeline run pipelines/ablation_synthetic.yaml --until motion --cache CACHE
    python3 docs/scripts/motion_window_probe.py CACHE
"""
import zarr, numpy as np, glob, sys
CACHE = sys.argv[1] if len(sys.argv) > 1 else 'cache'
def entry(kind):
    found = [p for p in glob.glob(f'{CACHE}/{kind}/*') if not p.endswith('.complete')]
    if not found:
        sys.exit(f'{CACHE}/{kind}: no entry (run the pipeline --until motion first)')
    return found[0]
ing = zarr.open_group(entry('ingest'), mode='r')
mot = zarr.open_group(entry('motion'), mode='r')
G = ing['garment_state'][:]                       # (F, 6)
T = ing['body_world_translation'][:]              # (F, 3)
Rv = ing['body_world_rotation'][:]                # (F, 3) axis-angle
pose = ing['body_pose'][:].reshape(G.shape[0], -1)
hist = ing['history_frame'][:].astype(bool)
F = G.shape[0]
def rotmat(a):
    th = np.linalg.norm(a)
    if th < 1e-12: return np.eye(3)
    k = a / th; K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
def logm(R):
    c = np.clip((np.trace(R) - 1) / 2, -1, 1); th = np.arccos(c)
    if th < 1e-9: return np.zeros(3)
    return th / (2 * np.sin(th)) * np.array([R[2,1]-R[1,2], R[0,2]-R[2,0], R[1,0]-R[0,1]])
R = np.stack([rotmat(a) for a in Rv])
posed = mot['posed_vertices']
cv = mot['canonical_vertices'][:]
y = cv[:, 1]; band = (y > np.percentile(y, 35)) & (y < np.percentile(y, 55))   # hip band
P = np.stack([posed[t][band].mean(0) for t in range(F)])                      # (F, 3) hip-band centre, world
def feats(scales, L, cur_pose=True, world=False, own=False):
    rows = []
    for t in range(F):
        Rt = np.eye(3) if world else R[t].T   # world -> body frame of frame t
        f = [pose[t]] if cur_pose else []
        for s in scales:
            for l in range(L):
                c, p = max(t - l * s, 0), max(t - (l + 1) * s, 0)
                f.append((R[c].T if own else Rt) @ (P[c] - P[p]) / s)
                f.append(logm(R[c] @ R[p].T))
        rows.append(np.concatenate(f) if f else np.zeros(1))
    X = np.array(rows); X = (X - X.mean(0)) / (X.std(0) + 1e-9)
    return X
def cv_r2(X, Y, lams=(0.1, 1, 10, 100, 1000)):
    Y = (Y - Y.mean(0)) / (Y.std(0) + 1e-12)
    folds = np.arange(F) // 22 % 10    # contiguous blocks of ~22 frames
    best = -9
    for lam in lams:
        pred = np.zeros_like(Y)
        for k in range(10):
            tr, te = folds != k, folds == k
            Xt = np.c_[X[tr], np.ones(tr.sum())]
            W = np.linalg.solve(Xt.T @ Xt + lam * np.eye(Xt.shape[1]), Xt.T @ Y[tr])
            pred[te] = np.c_[X[te], np.ones(te.sum())] @ W
        r2 = 1 - ((pred - Y) ** 2)[hist].sum() / (Y[hist] ** 2).sum()
        best = max(best, r2)
    return best


print(f'{"pose only":25}: R2 {cv_r2(pose, G):.3f}  hem {cv_r2(pose, G[:, :2]):.3f}')
for name, sc, L in [('[6,3] L=2', [6,3], 2), ('[6,3] L=3', [6,3], 3), ('[12,6,3] L=4', [12,6,3], 4),
                    ('[24,12,6] L=4', [24,12,6], 4), ('[6,3] L=8', [6,3], 8)]:
    for mode in ('world', 'body of t', 'body of u'):
        X = feats(sc, L, world=(mode=='world'), own=(mode=='body of u'))
        print(f'{name:14} {mode:10}: R2 {cv_r2(X, G):.3f}  hem {cv_r2(X, G[:, :2]):.3f}  twist+rate {cv_r2(X, G[:, [2,5]]):.3f}')
