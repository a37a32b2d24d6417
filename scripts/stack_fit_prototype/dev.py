"""Development runner: one or a few cases with stackfit2 options given as JSON.

    python dev.py '{"hf": 0.0}' 10,39 7,29 5,27

Prints held-out mean, planes above baseline, the losing planes, fit/predict time.
Held-out planes are only *scored* here (development diagnostics), never fitted.
"""
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stackfit as sf  # noqa: E402
import stackfit2 as sf2  # noqa: E402
from bench import DATA  # noqa: E402

kw = json.loads(sys.argv[1])
pairs = [tuple(int(x) for x in a.split(",")) for a in sys.argv[2:]]
raw = np.load(DATA)["psf_stack"].astype(np.float64) / 65535.0
stack = sf.preprocess(raw)
n = stack.shape[0]
out = []
for i, j in pairs:
    held = [t for t in range(n) if t not in (i, j)]
    imgs = [stack[i].astype(np.float32), stack[j].astype(np.float32)]
    reg = sf.register(imgs[0], imgs[1])
    base = sf.baseline_stack({i: imgs[0], j: imgs[1]}, reg, n)
    rb = np.array([sf.pearson(base[t], stack[t]) for t in held])
    fit = sf2.fit_wave(imgs, i, j, reg, **kw)
    t0 = time.time()
    pred = sf2.predict_stack(fit, n)
    tp = time.time() - t0
    r = np.array([sf.pearson(pred[t], stack[t]) for t in held])
    t0 = time.time()
    hyb = sf2.predict_hybrid(fit, imgs, n, model_stack=pred)
    th = time.time() - t0
    rh = np.array([sf.pearson(hyb[t], stack[t]) for t in held])
    bl = sf2.blended_baseline({i: imgs[0], j: imgs[1]}, reg, n)
    rbl = np.array([sf.pearson(bl[t], stack[t]) for t in held])
    dh = rh - rb
    print(f"   HYBRID mean {rh.mean():.4f} min {rh.min():.4f} beats {(dh > 0).sum()}/42 "
          f"min d {dh.min():+.4f}@{held[int(dh.argmin())]} (+{th:.1f}s) | "
          f"blended baseline {rbl.mean():.4f} beats-base {(rbl > rb).sum()}/42")
    d = r - rb
    lose = " ".join(f"{t}({x:+.4f})" for t, x in zip(held, d) if x <= 0)
    sc = {k: round(float(v), 4) for k, v in fit.params.items() if np.ndim(v) == 0}
    print(f"({i},{j}) mean {r.mean():.4f} base {rb.mean():.4f} min {r.min():.4f}@"
          f"{held[int(r.argmin())]} beats {(d > 0).sum()}/42 fit {fit.seconds:.1f}s "
          f"pred {tp:.1f}s steps {fit.best_step}/{fit.steps} "
          f"val {max(fit.val_history):.4f} train {fit.train_history[fit.best_step]:.4f} "
          f"| {fit.stop_reason} | {sc}\n   lose: {lose}", flush=True)
    out.append(r.mean())
    np.savez(f"/tmp/dev_{i}_{j}.npz", pred=pred, r=r, rb=rb, held=held,
             val=np.array(fit.val_history), train=np.array(fit.train_history),
             **{k: np.asarray(v) for k, v in fit.params.items()})
    print("   model-base: " + " ".join(f"{t}:{x:+.3f}" for t, x in zip(held, d)))
print(f"dev mean {np.mean(out):.4f}  load {open('/proc/loadavg').read().split()[:3]}")
