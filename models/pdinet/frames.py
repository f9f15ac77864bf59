"""Synthetic thermal frames and a radial blur map, enough to give BatchNorm realistic statistics.

Frames: a cool sky above a warmer ground with a vertical gradient, low-frequency texture,
a few warm elliptical objects, sensor noise; values in [0, 1] like a normalised 14-bit frame.
The blur map grows off-axis like the single-lens camera's (field curvature dominates).
"""
import numpy as np


def blur_map_radial(rows=6, cols=8):
    y, x = np.meshgrid((np.arange(rows) + 0.5) / rows - 0.5, (np.arange(cols) + 0.5) / cols - 0.5,
                       indexing="ij")
    r2 = (x * 4 / 3) ** 2 + y ** 2  # 4:3 sensor aspect
    k = r2 / r2.max()
    return ((k - k.min()) / (k.max() - k.min())).astype(np.float32)


def thermal_frames(batches, batch_size, h, w, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for _ in range(batches):
        batch = np.empty((batch_size, 1, h, w), np.float32)
        for b in range(batch_size):
            horizon = rng.uniform(0.3, 0.6) * h
            sky = 0.15 + 0.05 * yy / h
            ground = 0.35 + 0.15 * (yy - horizon) / h
            img = np.where(yy < horizon, sky, ground)
            fx, fy = rng.uniform(1, 6, 2)
            img += 0.03 * np.sin(2 * np.pi * fx * xx / w + rng.uniform(0, 6)) * np.cos(
                2 * np.pi * fy * yy / h + rng.uniform(0, 6))
            for _ in range(rng.integers(2, 9)):
                cx, cy = rng.uniform(0, w), rng.uniform(horizon, h)
                ax, ay = rng.uniform(3, w / 10), rng.uniform(3, h / 8)
                img += rng.uniform(0.2, 0.5) * np.exp(-(((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2) ** 2)
            img += rng.normal(0, 0.01, img.shape)
            batch[b, 0] = np.clip(img, 0, 1)
        out.append(batch)
    return out
