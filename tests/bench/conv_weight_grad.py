"""Times ways to compute a 1D convolution's weight gradient on this CPU, at the ValueFunction
reward's layer sizes (issue 38): what `blocks::second_order::conv_weight_grad` computes once per
convolution per training step, over a stacked batch of 2 B (the values and their tangents).

- `convolution`: the inputs transposed to [C, N, L] convolved with the adjoints transposed to
  [O, N, L'] as the kernel, the stride as the dilation (what relreward does: tch binds no
  convolution backward);
- `im2col`: unfold and one matrix product (tensordot);
- `aten`: libtorch's own `convolution_backward` (weight only), for reference: tch does not bind
  it.

Also the forward convolution and the transposed one (the input's backward) at the same sizes.
Best of five rounds, one thread; microseconds. Each way's largest difference from aten's is
printed beside it.

    .venv/bin/python tests/bench/conv_weight_grad.py
"""

import time

import torch
import torch.nn.functional as F


def best_us(f, n=30):
    for _ in range(3):
        f()
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(n):
            f()
        best = min(best, (time.perf_counter() - start) / n)
    return best * 1e6


def main():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    # (B, C_in, C_out, L, kernel, stride, padding): a level-0 block, a level-3 block, a
    # downsampling and the first block's 14 input channels, at the serving benchmark's size.
    layers = [(64, 64, 64, 32, 5, 1, 2), (64, 128, 128, 4, 5, 1, 2), (64, 64, 64, 32, 3, 2, 1),
              (64, 14, 64, 32, 5, 1, 2)]
    print("| N x C_in -> C_out, L, k, stride | forward | transposed | convolution | im2col | aten |")
    print("|---|---|---|---|---|---|")
    for b, c, o, length, k, stride, pad in layers:
        x = torch.randn(2 * b, c, length)
        w = torch.randn(o, c, k)
        y = F.conv1d(x, w, None, stride, pad)
        g = torch.randn_like(y)
        out_pad = length - ((y.shape[2] - 1) * stride - 2 * pad + k)

        def convolution():
            dw = F.conv1d(x.transpose(0, 1), g.transpose(0, 1), None, 1, pad, stride)
            return dw[:, :, :k].transpose(0, 1).contiguous()

        def im2col():
            cols = F.unfold(x.unsqueeze(2), (1, k), 1, (0, pad), (1, stride))
            return torch.tensordot(g, cols, dims=([0, 2], [0, 2])).view(o, c, k)

        def aten():
            return torch.ops.aten.convolution_backward(g, x, w, None, [stride], [pad], [1], False, [0], 1,
                                                       [False, True, False])[1]

        want = aten()
        scale = float(want.abs().max())
        err = {f.__name__: float((f() - want).abs().max()) / scale for f in (convolution, im2col)}
        times = [best_us(lambda: F.conv1d(x, w, None, stride, pad)),
                 best_us(lambda: F.conv_transpose1d(g, w, None, stride, pad, out_pad)),
                 best_us(convolution), best_us(im2col), best_us(aten)]
        print(f"| {2 * b} x {c} -> {o}, {length}, {k}, {stride} | {times[0]:.0f} | {times[1]:.0f} | "
              f"{times[2]:.0f} (rel. diff {err['convolution']:.0e}) | {times[3]:.0f} (rel. diff {err['im2col']:.0e}) | "
              f"{times[4]:.0f} |")


if __name__ == "__main__":
    main()
