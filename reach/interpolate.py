"""Multilinear interpolation on a `Grid` in torch (batched, any device, any dimension)."""

import torch


class GridInterpolator:
    """Precomputes corner indices and weights of query points; `__call__` then
    interpolates any node array of the grid's shape at those points (a gather).

    Points outside the box are clamped to it (the caller decides what that means)."""

    def __init__(self, grid, points: torch.Tensor):
        n = grid.ndim
        lo = torch.as_tensor(grid.lo, dtype=points.dtype, device=points.device)
        spacing = torch.as_tensor(grid.spacing, dtype=points.dtype, device=points.device)
        shape = torch.as_tensor(grid.shape, device=points.device)
        u = (points.reshape(-1, n) - lo) / spacing
        u = torch.minimum(torch.clamp(u, min=0.0), (shape - 1).to(points.dtype))
        i0 = torch.minimum(u.floor().long(), shape - 2)
        w = u - i0
        strides = [1] * n
        for k in range(n - 2, -1, -1):
            strides[k] = strides[k + 1] * grid.shape[k + 1]
        strides = torch.tensor(strides, device=points.device)
        self.indices, self.weights = [], []
        for corner in range(2 ** n):
            bits = torch.tensor([(corner >> k) & 1 for k in range(n)], device=points.device)
            self.indices.append(((i0 + bits) * strides).sum(-1))
            self.weights.append(torch.where(bits.bool(), w, 1.0 - w).prod(-1))
        self.indices = torch.stack(self.indices)          # (2^n, N)
        self.weights = torch.stack(self.weights)          # (2^n, N)
        self.out_shape = points.shape[:-1]

    def __call__(self, values: torch.Tensor) -> torch.Tensor:
        flat = values.reshape(-1)
        return (flat[self.indices] * self.weights).sum(0).reshape(self.out_shape)
