"""Multilinear interpolation on a `Grid` in torch (batched, any device)."""

import torch


class GridInterpolator:
    """Precomputes corner indices and weights of query points; `__call__` then
    interpolates any node array of the grid's shape at those points (a gather).

    Points outside the box are clamped to it (the caller decides what that means)."""

    def __init__(self, grid, points: torch.Tensor):
        lo = torch.as_tensor(grid.lo, dtype=points.dtype, device=points.device)
        spacing = torch.as_tensor(grid.spacing, dtype=points.dtype, device=points.device)
        shape = torch.as_tensor(grid.shape, device=points.device)
        u = (points.reshape(-1, 3) - lo) / spacing
        u = torch.minimum(torch.clamp(u, min=0.0), (shape - 1).to(points.dtype))
        i0 = torch.minimum(u.floor().long(), shape - 2)
        w = u - i0
        strides = torch.tensor([grid.shape[1] * grid.shape[2], grid.shape[2], 1],
                               device=points.device)
        self.indices, self.weights = [], []
        for corner in range(8):
            bits = torch.tensor([(corner >> k) & 1 for k in range(3)], device=points.device)
            self.indices.append(((i0 + bits) * strides).sum(-1))
            self.weights.append(torch.where(bits.bool(), w, 1.0 - w).prod(-1))
        self.indices = torch.stack(self.indices)          # (8, N)
        self.weights = torch.stack(self.weights)          # (8, N)
        self.out_shape = points.shape[:-1]

    def __call__(self, values: torch.Tensor) -> torch.Tensor:
        flat = values.reshape(-1)
        return (flat[self.indices] * self.weights).sum(0).reshape(self.out_shape)
