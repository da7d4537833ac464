"""A float64 numpy re-implementation of the 3DGS render formulas, written
independently of mlx3d.render (loops, no tiles shared), for small test scenes.

EWA projection with the frustum clamp, blur, radius = ceil(3 sqrt(λmax)),
tile rule and the per-pixel front-to-back loop of docs/guides/rendering.md,
optionally with a surface layer (mlx3d.render.surface) composited in depth order.
"""

import math

import numpy as np


def quat_to_rot(q):
    w, x, y, z = np.asarray(q, np.float64) / math.sqrt(float(np.dot(q, q)) + 1e-24)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def project_one(cam, mean, quat, scale, blur=0.3):
    """(mean2d, conic, radius, depth) of one Gaussian, radius 0 when culled."""
    view = np.asarray(cam.viewmat, np.float64)
    p = view[:3, :3] @ mean + view[:3, 3]
    x, y, z = p
    if not (cam.near <= z <= cam.far):
        return None, None, 0, z
    tan_x, tan_y = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    lim_xp, lim_xn = (cam.width - cam.cx) / cam.fx + 0.3 * tan_x, cam.cx / cam.fx + 0.3 * tan_x
    lim_yp, lim_yn = (cam.height - cam.cy) / cam.fy + 0.3 * tan_y, cam.cy / cam.fy + 0.3 * tan_y
    tx = z * min(lim_xp, max(-lim_xn, x / z))
    ty = z * min(lim_yp, max(-lim_yn, y / z))
    jac = np.array([[cam.fx / z, 0, -cam.fx * tx / z**2], [0, cam.fy / z, -cam.fy * ty / z**2]])
    m = quat_to_rot(quat) @ np.diag(scale)
    cov = view[:3, :3] @ (m @ m.T) @ view[:3, :3].T
    c2 = jac @ cov @ jac.T + blur * np.eye(2)
    det = c2[0, 0] * c2[1, 1] - c2[0, 1] ** 2
    if not det > 0:
        return None, None, 0, z
    conic = np.array([c2[1, 1], -c2[0, 1], c2[0, 0]]) / det
    mid = 0.5 * (c2[0, 0] + c2[1, 1])
    radius = math.ceil(3 * math.sqrt(mid + math.sqrt(max(0.1, mid * mid - det))))
    mean2d = np.array([cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy])
    if mean2d[0] + radius <= 0 or mean2d[0] - radius >= cam.width or mean2d[1] + radius <= 0 or mean2d[1] - radius >= cam.height:
        return None, None, 0, z
    return mean2d, conic, radius, z


def _surface_event(c, T, surface, i, j):
    """(c, T) after the surface layer (color (H,W,3), alpha (H,W), depth (H,W)) at pixel (i, j)."""
    color, alpha, _ = surface
    return c + T * np.asarray(color[i, j], np.float64), T * (1.0 - float(alpha[i, j]))


def render(cam, means, quats, scales, opacities, colors, background=None, tile=16, surface=None):
    """(image (H,W,3), alpha (H,W)) in float64. surface: None or numpy (color, alpha, depth), composited
    just before the first Gaussian with depth >= depth[i, j] (after the last if none) unless the pixel
    stopped; the pixel stops when the surface leaves T < 1e-4."""
    n = len(means)
    proj = [project_one(cam, means[i], quats[i], scales[i]) for i in range(n)]
    image = np.zeros((cam.height, cam.width, 3))
    alpha_img = np.zeros((cam.height, cam.width))
    for i in range(cam.height):
        for j in range(cam.width):
            tx, ty = j // tile, i // tile
            hits = []
            for g, (m2, conic, r, z) in enumerate(proj):
                if r > 0 and math.floor((m2[0] - r) / tile) <= tx <= math.floor((m2[0] + r) / tile) and math.floor((m2[1] - r) / tile) <= ty <= math.floor((m2[1] + r) / tile):
                    hits.append((np.float32(z), g))
            T, c = 1.0, np.zeros(3)
            pending, stopped = surface is not None, False
            for z, g in sorted(hits):
                if pending and z >= surface[2][i, j]:
                    pending = False
                    c, T = _surface_event(c, T, surface, i, j)
                    if T < 1e-4:
                        stopped = True
                        break
                m2, (a, b, cc), _, _ = proj[g]
                dx, dy = m2[0] - (j + 0.5), m2[1] - (i + 0.5)
                power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                if power > 0:
                    continue
                al = min(0.99, opacities[g] * math.exp(power))
                if al < 1 / 255:
                    continue
                if T * (1 - al) < 1e-4:
                    stopped = True
                    break
                c += colors[g] * al * T
                T *= 1 - al
            if pending and not stopped:
                c, T = _surface_event(c, T, surface, i, j)
            image[i, j] = c + (T * np.asarray(background) if background is not None else 0)
            alpha_img[i, j] = 1 - T
    return image, alpha_img
