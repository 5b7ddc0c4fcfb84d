#!/usr/bin/env python3
"""Draws a training run's learning curve as an SVG (no dependencies).

usage: plot_curve.py RUN_DIR OUT.svg
Top: training loss (EMA, left axis). Bottom: validation rotation acc@15° (one-shot
Procrustes, 48 views of held-out objects 750–799) and correspondence accuracy.
"""
import csv
import sys


def read(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def polyline(xs, ys, x0, x1, y0, y1, w, h, ox, oy, colour):
    pts = []
    for x, y in zip(xs, ys):
        px = ox + (x - x0) / max(x1 - x0, 1e-9) * w
        py = oy + h - (y - y0) / max(y1 - y0, 1e-9) * h
        pts.append(f"{px:.1f},{py:.1f}")
    return f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{" ".join(pts)}"/>'


def main():
    run, out = sys.argv[1], sys.argv[2]
    train = read(f"{run}/train.csv")
    val = read(f"{run}/val.csv")
    it = [int(r["iteration"]) for r in train]
    loss = [float(r["loss_avg"]) for r in train]
    vit = [int(r["iteration"]) for r in val]
    acc15 = [float(r["rotation_acc_15"]) for r in val]
    corr = [float(r["correspondence_accuracy"]) for r in val]
    W, H, M = 640, 200, 50
    x1 = max(it) if it else 1
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W + 2 * M}" height="{2 * H + 3 * M}" font-family="sans-serif" font-size="12">',
             '<rect width="100%" height="100%" fill="white"/>']
    for k, (title, lo, hi) in enumerate([("training loss (EMA)", min(loss), max(loss)),
                                         ("validation: rotation acc@15° (blue), correspondence acc (orange)", 0.0, 1.0)]):
        oy = M + k * (H + M)
        parts.append(f'<rect x="{M}" y="{oy}" width="{W}" height="{H}" fill="none" stroke="#888"/>')
        parts.append(f'<text x="{M}" y="{oy - 6}">{title}</text>')
        parts.append(f'<text x="{M - 45}" y="{oy + 10}">{hi:.2f}</text><text x="{M - 45}" y="{oy + H}">{lo:.2f}</text>')
        parts.append(f'<text x="{M}" y="{oy + H + 15}">0</text><text x="{M + W - 30}" y="{oy + H + 15}">{x1}</text>')
        if k == 0:
            parts.append(polyline(it, loss, 0, x1, lo, hi, W, H, M, oy, "black"))
        else:
            parts.append(polyline(vit, acc15, 0, x1, lo, hi, W, H, M, oy, "#1f77b4"))
            parts.append(polyline(vit, corr, 0, x1, lo, hi, W, H, M, oy, "#ff7f0e"))
    parts.append(f'<text x="{M + W / 2 - 30}" y="{2 * H + 3 * M - 10}">iteration</text></svg>')
    with open(out, "w") as f:
        f.write("\n".join(parts))


if __name__ == "__main__":
    main()
