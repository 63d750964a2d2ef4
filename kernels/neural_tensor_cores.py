"""The learned residual's fused training step on a GPU's tensor cores: the same work as
``kernels.neural_training.make_train_tiles`` (codes gathered, the decoder forward, the squared error, the whole
backward pass, the codes' gradients added at their pixels, each block's sums of the weights' gradients stored), with
its matrix products as TF32 tensor-core instructions (``mma.sync.m16n8k8``: inputs rounded to TF32, 10 bits of
mantissa; sums in float32).

A block of 256 threads (8 warps) takes 128 samples a pass, ``passes`` passes:

1. the block gathers the 128 samples' inputs (codes, light features, a constant one) into shared memory;
2. each warp runs its 16 samples through the decoder and back in registers (a layer's output fragments are the next
   layer's input fragments: the products' inner index is ordered so that they line up), leaving the activations and
   the pre-activations' gradients in shared memory, and adding its codes' gradients at their pixels;
3. each warp adds its share of the weights' gradients (activations times gradients, summed over the 128 samples) to
   fragments it keeps in registers for all its passes; they are stored once, as the block's partial sums, after the
   last pass.

CUDA only (compute capability 8.0 or newer): the body is empty when compiled for the CPU. The shapes are the decoder's
(``kernels.neural``): 14 inputs (9 code numbers, 3 direction, sqrt(g), g), three hidden layers of 48, 3 outputs.
"""

from __future__ import annotations

import functools

import warp as wp

from .neural import CODE_SIZE, HIDDEN, INPUTS, OUTPUTS

__all__ = ["MIN_ARCH", "SAMPLES_PER_PASS", "SHARED_FLOATS", "THREADS", "make_tensor_core_step"]

THREADS = 256
"""Threads a block: 8 warps of 16 samples each."""
SAMPLES_PER_PASS = 128
"""Samples a block takes a pass."""
MIN_ARCH = 80
"""The oldest GPU architecture with TF32 ``mma.sync`` (NVIDIA Ampere, compute capability 8.0)."""

if (int(HIDDEN), int(INPUTS), int(CODE_SIZE), int(OUTPUTS)) != (48, 14, 9, 3):
    raise ImportError("the tensor-core step is written for a decoder of 14 inputs, 3 x 48 hidden units and 3 outputs")

# Shared memory, in floats. Row strides are chosen so that a warp's fragment loads fall on distinct banks.
_LAYOUT = {
    "W0": (48, 24),  # w0, (unit, input); inputs 14..23 zero
    "W1": (48, 56),  # w1, (unit, input); inputs 48..55 zero
    "W2": (48, 56),
    "W3": (8, 56),  # w3, (output, input); outputs 3..7 zero
    "W3T": (48, 8),  # w3 transposed, (input, output)
    "B": (1, 3 * 48 + 8),  # b0, b1, b2 (48 each), b3 (8, 3 used)
    "X": (SAMPLES_PER_PASS, 24),  # inputs, (sample, input); input 14 is 1 (for b0's gradient), 15..23 zero
    "H": (3 * SAMPLES_PER_PASS, 56),  # h1, h2, h3, (sample, unit); unit 48 is 1 (for the biases' gradients)
    "D": (3 * SAMPLES_PER_PASS, 56),  # the gradients of the three hidden layers' pre-activations
    "DY": (SAMPLES_PER_PASS, 8),  # the outputs' gradients; 3..7 zero
    "PIX": (1, SAMPLES_PER_PASS),  # the samples' pixels (int32)
}
_OFFSETS = {}
_total = 0
for _name, (_rows, _cols) in _LAYOUT.items():
    _OFFSETS[_name] = _total
    _total += _rows * _cols
SHARED_FLOATS = _total
"""Shared memory a block uses, in floats (about 214 KiB: one block a multiprocessor on Hopper and Ampere)."""

_SNIPPET = (
    "#if defined(__CUDA_ARCH__)\n"
    + "".join(f"constexpr int OFF_{name} = {offset};\n" for name, offset in _OFFSETS.items())
    + r"""
constexpr int H = 48, NI = 14, NC = 9, NO = 3, S = 128;
constexpr int W0S = 24, WS = 56, W3TS = 8, XS = 24, HS = 56, YS = 8;
#define WHL_AT3(a, i, j, k) (*(float*)((char*)(a).data + (size_t)(i) * (a).strides[0] + (size_t)(j) * (a).strides[1] \
                                       + (size_t)(k) * (a).strides[2]))
#define WHL_AT4(a, i, j, k, l) (*(float*)((char*)(a).data + (size_t)(i) * (a).strides[0] \
                                          + (size_t)(j) * (a).strides[1] + (size_t)(k) * (a).strides[2] \
                                          + (size_t)(l) * (a).strides[3]))
extern __shared__ __align__(16) float whl_training_smem[];
float* const sm = whl_training_smem;
int* const pix = reinterpret_cast<int*>(sm + OFF_PIX);
const int warp = lane >> 5, g = (lane & 31) >> 2, t = lane & 3;

typedef float whl_frag[4];      // a fragment: 4 numbers a thread
typedef float whl_frags[6][4];  // 6 fragments: 16 samples by 48 units
auto tf32 = [](float x) -> float {
    unsigned r;
    asm("cvt.rna.tf32.f32 %0, %1;" : "=r"(r) : "f"(x));
    return __uint_as_float(r);
};
auto mma = [](whl_frag& c, float a0, float a1, float a2, float a3, float p0, float p1) {
    asm("mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};"
        : "+f"(c[0]), "+f"(c[1]), "+f"(c[2]), "+f"(c[3])
        : "r"(__float_as_uint(a0)), "r"(__float_as_uint(a1)), "r"(__float_as_uint(a2)), "r"(__float_as_uint(a3)),
          "r"(__float_as_uint(p0)), "r"(__float_as_uint(p1)));
};
auto elu = [](float x) -> float { return x > 0.f ? x : __expf(fminf(x, 0.f)) - 1.f; };
auto elu_slope = [](float out) -> float { return out > 0.f ? 1.f : out + 1.f; };
auto pair = [](float* p) -> float2& { return *reinterpret_cast<float2*>(p); };

// The weights, rounded to TF32, and the constant parts of the staging rows.
for (int e = lane; e < OFF_X; e += 256) sm[e] = 0.f;
__syncthreads();
for (int e = lane; e < H * NI; e += 256) sm[OFF_W0 + (e / NI) * W0S + e % NI] = tf32(WHL_AT3(w0, m, e / NI, e % NI));
for (int e = lane; e < H * H; e += 256) {
    sm[OFF_W1 + (e / H) * WS + e % H] = tf32(WHL_AT3(w1, m, e / H, e % H));
    sm[OFF_W2 + (e / H) * WS + e % H] = tf32(WHL_AT3(w2, m, e / H, e % H));
}
for (int e = lane; e < NO * H; e += 256) {
    const float v = tf32(WHL_AT3(w3, m, e / H, e % H));
    sm[OFF_W3 + (e / H) * WS + e % H] = v;
    sm[OFF_W3T + (e % H) * W3TS + e / H] = v;
}
for (int e = lane; e < H; e += 256) {
    sm[OFF_B + e] = WHL_AT3(b0, m, e, 0);
    sm[OFF_B + H + e] = WHL_AT3(b1, m, e, 0);
    sm[OFF_B + 2 * H + e] = WHL_AT3(b2, m, e, 0);
}
if (lane < NO) sm[OFF_B + 3 * H + lane] = WHL_AT3(b3, m, lane, 0);
for (int s = lane; s < S; s += 256) {
    for (int c = NI; c < XS; ++c) sm[OFF_X + s * XS + c] = c == NI ? 1.f : 0.f;
    for (int l = 0; l < 3; ++l)
        for (int c = H; c < HS; ++c) sm[OFF_H + (l * S + s) * HS + c] = c == H ? 1.f : 0.f;
}

// The weights' gradients this warp sums: warps 0-2 w1's rows 16w..16w+15, warps 3-5 w2's, warp 6 w3's (rows 0-2 of
// a 16-row fragment), each with its 7 column fragments (inputs 0..55: the bias's gradient is column 48); warp 7 w0's
// 3 row fragments by 2 column fragments (inputs 0..15: b0's gradient is column 14).
float acc[7][4];
#pragma unroll
for (int n = 0; n < 7; ++n)
#pragma unroll
    for (int q = 0; q < 4; ++q) acc[n][q] = 0.f;
float squares = 0.f;
const float slope = 2.f * scale;
const int r0 = warp * 16;  // this warp's rows in phase 2

for (int pass = 0; pass < passes; ++pass) {
    const int base = (block * passes + pass) * S;
    __syncthreads();  // the previous pass's reads are done
    for (int e = lane; e < S * NI; e += 256) {
        const int s = e % S, f = e / S;
        float v;
        if (f < NC) {
            const int p = pixel_index.data[base + s];
            if (f == 0) pix[s] = p;
            v = WHL_AT3(codes, m, f, p);
        } else {
            v = WHL_AT3(light_features, m, f - NC, base + s);
        }
        sm[OFF_X + s * XS + f] = tf32(v);
    }
    __syncthreads();

    // ---- phase 2: this warp's 16 samples forward and back
    float* const x = sm + OFF_X;
    float* const h1s = sm + OFF_H;
    float* const h2s = h1s + S * HS;
    float* const h3s = h2s + S * HS;
    float* const d1s = sm + OFF_D;
    float* const d2s = d1s + S * HS;
    float* const d3s = d2s + S * HS;
    const int ra = (r0 + g) * HS, rb = (r0 + g + 8) * HS;

    float h1[6][4], h2[6][4], h3[6][4];
#pragma unroll
    for (int n = 0; n < 6; ++n) {
        const float lo = sm[OFF_B + 8 * n + 2 * t], hi = sm[OFF_B + 8 * n + 2 * t + 1];
        h1[n][0] = lo; h1[n][1] = hi; h1[n][2] = lo; h1[n][3] = hi;
    }
#pragma unroll
    for (int j = 0; j < 2; ++j) {
        const float2 xa = pair(x + (r0 + g) * XS + 8 * j + 2 * t), xb = pair(x + (r0 + g + 8) * XS + 8 * j + 2 * t);
#pragma unroll
        for (int n = 0; n < 6; ++n) {
            const float2 w = pair(sm + OFF_W0 + (8 * n + g) * W0S + 8 * j + 2 * t);
            mma(h1[n], xa.x, xb.x, xa.y, xb.y, w.x, w.y);
        }
    }
#pragma unroll
    for (int n = 0; n < 6; ++n) {
#pragma unroll
        for (int q = 0; q < 4; ++q) h1[n][q] = tf32(elu(h1[n][q]));
        pair(h1s + ra + 8 * n + 2 * t) = make_float2(h1[n][0], h1[n][1]);
        pair(h1s + rb + 8 * n + 2 * t) = make_float2(h1[n][2], h1[n][3]);
    }
    // a hidden layer: out = elu(in W^T + b), in's fragments as the product's left operand
    auto hidden = [&](const whl_frags& in, whl_frags& out, const float* W, const float* bias, float* store) {
#pragma unroll
        for (int n = 0; n < 6; ++n) {
            const float lo = bias[8 * n + 2 * t], hi = bias[8 * n + 2 * t + 1];
            out[n][0] = lo; out[n][1] = hi; out[n][2] = lo; out[n][3] = hi;
        }
#pragma unroll
        for (int j = 0; j < 6; ++j) {
#pragma unroll
            for (int n = 0; n < 6; ++n) {
                const float2 w = pair(const_cast<float*>(W) + (8 * n + g) * WS + 8 * j + 2 * t);
                mma(out[n], in[j][0], in[j][2], in[j][1], in[j][3], w.x, w.y);
            }
        }
#pragma unroll
        for (int n = 0; n < 6; ++n) {
#pragma unroll
            for (int q = 0; q < 4; ++q) out[n][q] = tf32(elu(out[n][q]));
            pair(store + ra + 8 * n + 2 * t) = make_float2(out[n][0], out[n][1]);
            pair(store + rb + 8 * n + 2 * t) = make_float2(out[n][2], out[n][3]);
        }
    };
    hidden(h1, h2, sm + OFF_W1, sm + OFF_B + H, h2s);
    hidden(h2, h3, sm + OFF_W2, sm + OFF_B + 2 * H, h3s);

    // the outputs (8 columns, 3 used), the squared error and its gradient
    float y[4];
    y[0] = y[2] = sm[OFF_B + 3 * H + 2 * t];
    y[1] = y[3] = sm[OFF_B + 3 * H + 2 * t + 1];
#pragma unroll
    for (int j = 0; j < 6; ++j) {
        const float2 w = pair(sm + OFF_W3 + g * WS + 8 * j + 2 * t);
        mma(y, h3[j][0], h3[j][2], h3[j][1], h3[j][3], w.x, w.y);
    }
    float dy[4];
#pragma unroll
    for (int q = 0; q < 4; ++q) {
        const int column = 2 * t + (q & 1), row = r0 + g + (q >> 1) * 8;
        dy[q] = 0.f;
        if (column < NO) {
            const float error = y[q] - WHL_AT3(batch_targets, m, column, base + row);
            squares += error * error;
            dy[q] = tf32(slope * error);
        }
    }
    pair(sm + OFF_DY + (r0 + g) * YS + 2 * t) = make_float2(dy[0], dy[1]);
    pair(sm + OFF_DY + (r0 + g + 8) * YS + 2 * t) = make_float2(dy[2], dy[3]);

    // back through w3: the gradient of h3, then of its pre-activation
    float d3[6][4];
#pragma unroll
    for (int n = 0; n < 6; ++n) {
#pragma unroll
        for (int q = 0; q < 4; ++q) d3[n][q] = 0.f;
        const float2 w = pair(sm + OFF_W3T + (8 * n + g) * W3TS + 2 * t);
        mma(d3[n], dy[0], dy[2], dy[1], dy[3], w.x, w.y);
#pragma unroll
        for (int q = 0; q < 4; ++q) d3[n][q] = tf32(d3[n][q] * elu_slope(h3[n][q]));
        pair(d3s + ra + 8 * n + 2 * t) = make_float2(d3[n][0], d3[n][1]);
        pair(d3s + rb + 8 * n + 2 * t) = make_float2(d3[n][2], d3[n][3]);
    }
    // back through a hidden layer's weights W (rows: its outputs): out = (in W) * elu'(its input, read from act)
    auto back = [&](const whl_frags& in, whl_frags& out, const float* W, const float* act, float* store) {
#pragma unroll
        for (int n = 0; n < 6; ++n)
#pragma unroll
            for (int q = 0; q < 4; ++q) out[n][q] = 0.f;
#pragma unroll
        for (int j = 0; j < 6; ++j) {
#pragma unroll
            for (int n = 0; n < 6; ++n) {
                const float b0v = W[(8 * j + 2 * t) * WS + 8 * n + g], b1v = W[(8 * j + 2 * t + 1) * WS + 8 * n + g];
                mma(out[n], in[j][0], in[j][2], in[j][1], in[j][3], b0v, b1v);
            }
        }
#pragma unroll
        for (int n = 0; n < 6; ++n) {
            const float2 ha = pair(const_cast<float*>(act) + ra + 8 * n + 2 * t);
            const float2 hb = pair(const_cast<float*>(act) + rb + 8 * n + 2 * t);
            out[n][0] = tf32(out[n][0] * elu_slope(ha.x));
            out[n][1] = tf32(out[n][1] * elu_slope(ha.y));
            out[n][2] = tf32(out[n][2] * elu_slope(hb.x));
            out[n][3] = tf32(out[n][3] * elu_slope(hb.y));
            pair(store + ra + 8 * n + 2 * t) = make_float2(out[n][0], out[n][1]);
            pair(store + rb + 8 * n + 2 * t) = make_float2(out[n][2], out[n][3]);
        }
    };
    back(d3, h3, sm + OFF_W2, h2s, d2s);  // h3 is free: it holds d2
    back(h3, h2, sm + OFF_W1, h1s, d1s);  // h2 holds d1
    // back through w0 to the inputs: the codes' gradients, added at the samples' pixels
#pragma unroll
    for (int n = 0; n < 2; ++n) {
        float dx[4] = {0.f, 0.f, 0.f, 0.f};
#pragma unroll
        for (int j = 0; j < 6; ++j) {
            const float b0v = sm[OFF_W0 + (8 * j + 2 * t) * W0S + 8 * n + g];
            const float b1v = sm[OFF_W0 + (8 * j + 2 * t + 1) * W0S + 8 * n + g];
            mma(dx, h2[j][0], h2[j][2], h2[j][1], h2[j][3], b0v, b1v);
        }
#pragma unroll
        for (int q = 0; q < 4; ++q) {
            const int input = 8 * n + 2 * t + (q & 1), row = r0 + g + (q >> 1) * 8;
            if (input < NC) atomicAdd(&WHL_AT3(code_gradients, m, input, pix[row]), dx[q]);
        }
    }
    __syncthreads();

    // ---- phase 3: this warp's share of the weights' gradients, summed over the pass's 128 samples
    if (warp < 7) {
        const float* A;
        const float* Bm;
        int as, m0;
        if (warp < 3) { A = d2s; Bm = h1s; as = HS; m0 = 16 * warp; }
        else if (warp < 6) { A = d3s; Bm = h2s; as = HS; m0 = 16 * (warp - 3); }
        else { A = sm + OFF_DY; Bm = h3s; as = YS; m0 = 0; }
        const bool upper = warp < 6;  // rows m0+8.. exist (not for w3's 8-row gradient)
#pragma unroll 2
        for (int k = 0; k < S; k += 8) {
            const float a0 = A[(k + t) * as + m0 + g], a2 = A[(k + t + 4) * as + m0 + g];
            const float a1 = upper ? A[(k + t) * as + m0 + g + 8] : 0.f;
            const float a3 = upper ? A[(k + t + 4) * as + m0 + g + 8] : 0.f;
#pragma unroll
            for (int n = 0; n < 7; ++n)
                mma(acc[n], a0, a1, a2, a3, Bm[(k + t) * HS + 8 * n + g], Bm[(k + t + 4) * HS + 8 * n + g]);
        }
    } else {
#pragma unroll 2
        for (int k = 0; k < S; k += 8) {
            float b[2][2];
#pragma unroll
            for (int n = 0; n < 2; ++n) {
                b[n][0] = x[(k + t) * XS + 8 * n + g];
                b[n][1] = x[(k + t + 4) * XS + 8 * n + g];
            }
#pragma unroll
            for (int mt = 0; mt < 3; ++mt) {
                const float a0 = d1s[(k + t) * HS + 16 * mt + g], a1 = d1s[(k + t) * HS + 16 * mt + g + 8];
                const float a2 = d1s[(k + t + 4) * HS + 16 * mt + g], a3 = d1s[(k + t + 4) * HS + 16 * mt + g + 8];
#pragma unroll
                for (int n = 0; n < 2; ++n) mma(acc[2 * mt + n], a0, a1, a2, a3, b[n][0], b[n][1]);
            }
        }
    }
}

// the loss, and the block's partial sums of the weights' gradients
#pragma unroll
for (int offset = 16; offset > 0; offset >>= 1) squares += __shfl_xor_sync(0xffffffffu, squares, offset);
if ((lane & 31) == 0) atomicAdd(&loss.data[m * (loss.strides[0] / sizeof(float))], squares * scale);
if (warp < 7) {
#pragma unroll
    for (int n = 0; n < 7; ++n) {
#pragma unroll
        for (int q = 0; q < 4; ++q) {
            const int row = (warp < 6 ? 16 * (warp % 3) : 0) + g + (q >> 1) * 8, column = 8 * n + 2 * t + (q & 1);
            const float v = acc[n][q];
            if (warp < 3) {
                if (column < H) WHL_AT4(g1, block, m, row, column) = v;
                else if (column == H) WHL_AT4(c1, block, m, row, 0) = v;
            } else if (warp < 6) {
                if (column < H) WHL_AT4(g2, block, m, row, column) = v;
                else if (column == H) WHL_AT4(c2, block, m, row, 0) = v;
            } else if (row < NO) {
                if (column < H) WHL_AT4(g3, block, m, row, column) = v;
                else if (column == H) WHL_AT4(c3, block, m, row, 0) = v;
            }
        }
    }
} else {
#pragma unroll
    for (int mt = 0; mt < 3; ++mt)
#pragma unroll
        for (int n = 0; n < 2; ++n)
#pragma unroll
            for (int q = 0; q < 4; ++q) {
                const int row = 16 * mt + g + (q >> 1) * 8, column = 8 * n + 2 * t + (q & 1);
                if (column < NI) WHL_AT4(g0, block, m, row, column) = acc[2 * mt + n][q];
                else if (column == NI) WHL_AT4(c0, block, m, row, 0) = acc[2 * mt + n][q];
            }
}
#undef WHL_AT3
#undef WHL_AT4
#endif
"""
)


@wp.func_native(_SNIPPET)
def _tensor_core_step(light_features: wp.array3d[float], pixel_index: wp.array[wp.int32], codes: wp.array3d[float],
                      code_gradients: wp.array3d[float], batch_targets: wp.array3d[float], scale: float,
                      w0: wp.array3d[float], b0: wp.array3d[float], w1: wp.array3d[float], b1: wp.array3d[float],
                      w2: wp.array3d[float], b2: wp.array3d[float], w3: wp.array3d[float], b3: wp.array3d[float],
                      g0: wp.array4d[float], c0: wp.array4d[float], g1: wp.array4d[float], c1: wp.array4d[float],
                      g2: wp.array4d[float], c2: wp.array4d[float], g3: wp.array4d[float], c3: wp.array4d[float],
                      loss: wp.array2d[float], passes: int, m: int, block: int, lane: int): ...


@functools.cache
def make_tensor_core_step(passes: int):
    """The tensor-core step's kernel for blocks of ``passes`` passes of ``SAMPLES_PER_PASS`` samples, launched as
    ``wp.launch_tiled(kernel, dim=[M, blocks], block_dim=THREADS)`` with the arguments of
    ``kernels.neural_training.make_train_tiles``'s kernel (the same inputs and outputs)."""

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def train_tiles_tf32(light_features: wp.array3d[float], pixel_index: wp.array[wp.int32],
                         codes: wp.array3d[float], code_gradients: wp.array3d[float],
                         batch_targets: wp.array3d[float], scale: float,
                         w0: wp.array3d[float], b0: wp.array3d[float], w1: wp.array3d[float], b1: wp.array3d[float],
                         w2: wp.array3d[float], b2: wp.array3d[float], w3: wp.array3d[float], b3: wp.array3d[float],
                         g0: wp.array4d[float], c0: wp.array4d[float], g1: wp.array4d[float], c1: wp.array4d[float],
                         g2: wp.array4d[float], c2: wp.array4d[float], g3: wp.array4d[float], c3: wp.array4d[float],
                         loss: wp.array2d[float]):
        m, block, lane = wp.tid()
        # reserves the block's shared memory (the step addresses it as CUDA's dynamic shared memory)
        wp.tile_empty(shape=(SHARED_FLOATS,), dtype=float, storage="shared")
        _tensor_core_step(light_features, pixel_index, codes, code_gradients, batch_targets, scale,
                          w0, b0, w1, b1, w2, b2, w3, b3, g0, c0, g1, c1, g2, c2, g3, c3, loss, passes, m, block, lane)

    return train_tiles_tf32
