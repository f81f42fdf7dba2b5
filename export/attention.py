"""Multi-head self-attention (paper eqs. 2-3), written out so it exports to plain ONNX MatMul/Softmax."""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["MultiHeadSelfAttention"]


class MultiHeadSelfAttention(nn.Module):
    """Q = W_Q F, K = W_K F, V = W_V F per head; softmax(Q K^T / sqrt(d_head)) V; heads concatenated and
    projected back to `dim`.

    :param dim: token feature dimension (d_RGB + d_D for the fused map).
    :param heads: number of heads; d_head = dim / heads.
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"attention dim {dim} is not divisible by {heads} heads")
        self.heads, self.d_head = heads, dim // heads
        self.norm = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """:param x: (B, L, dim) tokens. :return: (B, L, dim) attention output (without the residual)."""
        b, n, d = x.shape
        qkv = self.qkv(self.norm(x)).reshape(b, n, 3, self.heads, self.d_head).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]                                   # (B, heads, L, d_head)
        att = torch.softmax((q * self.d_head ** -0.5) @ k.transpose(-2, -1), dim=-1)
        y = (att @ v).transpose(1, 2).reshape(b, n, d)
        return self.proj(y)
