// Fused CPU kernels of the decoder's training step (pipeline/btf/fast/fused.py; built by
// pipeline/btf/fast/kernels.py).
//
// torch has no single op for these: each replaces several memory passes over a chunk's
// (rows x 106) activations by one. The products are the storage type's (float32, float64, or
// bfloat16 rounded the way a bfloat16 matrix product rounds its output); sums are in the
// accumulator type (float64 for float64, float32 otherwise), in a fixed order.
//
// neural_btf::output_layer: the last layer's forward (rows x hidden -> rows x outputs), the
//   residual against the targets, the loss, and the backward into the last hidden layer:
//   its weight and bias gradients, the gradient at the hidden layer's pre-activation (the
//   returned tensor, through the ReLU) and that gradient's column sums (the previous layer's
//   bias gradient).
// neural_btf::relu_backward_: the gradient through a ReLU, in place, with its column sums
//   and/or the gradient of the product that made the layer from its input rows.
//
// As torch's threshold_backward, a ReLU passes the gradient where its output is not <= 0
// (a NaN output passes it). The input rows' zeros (the one-hot block) are skipped, so a
// zero times an infinite gradient adds nothing there instead of a NaN.

#include <ATen/ATen.h>
#include <torch/library.h>

#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

// -DNEURAL_BTF_GENERIC builds the plain loops only (the tests compare the two), and
// -DNEURAL_BTF_NAMESPACE=name registers the ops under another name.
#ifndef NEURAL_BTF_NAMESPACE
#define NEURAL_BTF_NAMESPACE neural_btf
#endif
#if !defined(NEURAL_BTF_GENERIC) && defined(__AVX512F__) && defined(__AVX512BW__) && \
    defined(__AVX512VL__)
#define NEURAL_BTF_AVX512 1  // float32 storage on 16 lanes
#include <immintrin.h>
#if defined(__AVX512BF16__)
#define NEURAL_BTF_AVX512_BF16 1  // and bfloat16 storage (its conversion instructions)
#endif
#endif

namespace {

// How a storage type loads into, rounds in and stores from its accumulator type.
template <typename T>
struct Plain {
  using Acc = T;
  using Raw = T;
  static Acc load(Raw x) { return x; }
  static Acc round(Acc x) { return x; }
  static Raw store(Acc x) { return x; }
};

struct BFloat16 {
  using Acc = float;
  using Raw = uint16_t;
  static float load(uint16_t x) {
    uint32_t bits = uint32_t(x) << 16;
    float f;
    std::memcpy(&f, &bits, 4);
    return f;
  }
  static uint16_t store(float f) {  // round to nearest, ties to even; NaN stays NaN
    uint32_t bits;
    std::memcpy(&bits, &f, 4);
    uint32_t rounded = (bits + 0x7FFFu + ((bits >> 16) & 1u)) >> 16;
    return f != f ? uint16_t(0x7FC0) : uint16_t(rounded);
  }
  static float round(float x) { return load(store(x)); }
};

template <typename S>
const typename S::Raw* raw(const at::Tensor& t) {
  return reinterpret_cast<const typename S::Raw*>(t.const_data_ptr());
}

template <typename S>
typename S::Raw* raw_mut(const at::Tensor& t) {
  return reinterpret_cast<typename S::Raw*>(t.mutable_data_ptr());
}

template <typename S, int O>
void output_layer_kernel(int64_t rows, int64_t hidden, const at::Tensor& a, const at::Tensor& w,
                         const at::Tensor& b, const at::Tensor& targets, double scale,
                         const at::Tensor& g, const at::Tensor& g_w, const at::Tensor& g_b,
                         const at::Tensor& g_b_hidden, const at::Tensor& loss) {
  using Acc = typename S::Acc;
  const auto* pa = raw<S>(a);
  const auto* pt = targets.const_data_ptr<Acc>();
  auto* pg = raw_mut<S>(g);
  auto* pgw = g_w.mutable_data_ptr<Acc>();
  auto* pgb = g_b.mutable_data_ptr<Acc>();
  auto* pgh = g_b_hidden.mutable_data_ptr<Acc>();
  std::vector<Acc> wf(O * hidden);
  Acc bias[O];
  for (int64_t i = 0; i < O * hidden; ++i) wf[i] = S::load(raw<S>(w)[i]);
  for (int j = 0; j < O; ++j) bias[j] = S::load(raw<S>(b)[j]);
  const Acc* pw = wf.data();
  double sum_squares = 0;
  for (int64_t r = 0; r < rows; ++r) {
    const auto* ar = pa + r * hidden;
    Acc gj[O];
    for (int j = 0; j < O; ++j) {
      const Acc* wj = pw + j * hidden;
      Acc s = 0;
#pragma omp simd reduction(+ : s)
      for (int64_t i = 0; i < hidden; ++i) s += S::load(ar[i]) * wj[i];
      Acc residual = S::round(s + bias[j]) - pt[r * O + j];
      sum_squares += double(residual) * double(residual);
      gj[j] = S::round(residual * Acc(scale));
      pgb[j] += gj[j];
    }
    auto* gr = pg + r * hidden;
#pragma omp simd
    for (int64_t i = 0; i < hidden; ++i) {
      Acc x = S::load(ar[i]);
      Acc h = 0;
      for (int j = 0; j < O; ++j) {
        h += gj[j] * pw[j * hidden + i];
        pgw[j * hidden + i] += gj[j] * x;
      }
      h = !(x <= 0) ? S::round(h) : Acc(0);
      gr[i] = S::store(h);
      pgh[i] += h;
    }
  }
  *loss.mutable_data_ptr<double>() += sum_squares;
}

template <typename S>
void relu_backward_kernel(int64_t rows, int64_t hidden, const at::Tensor& h, const at::Tensor& a,
                          const c10::optional<at::Tensor>& g_b, const c10::optional<at::Tensor>& x,
                          const c10::optional<at::Tensor>& g_x) {
  using Acc = typename S::Acc;
  auto* ph = raw_mut<S>(h);
  const auto* pa = raw<S>(a);
  Acc* pgb = g_b ? g_b->mutable_data_ptr<Acc>() : nullptr;
  const typename S::Raw* px = x ? raw<S>(*x) : nullptr;
  Acc* pgx = g_x ? g_x->mutable_data_ptr<Acc>() : nullptr;
  const int64_t inputs = x ? x->size(1) : 0;
  std::vector<Acc> row(hidden);
  for (int64_t r = 0; r < rows; ++r) {
    auto* hr = ph + r * hidden;
    const auto* ar = pa + r * hidden;
    Acc* v = row.data();
#pragma omp simd
    for (int64_t i = 0; i < hidden; ++i) {
      Acc value = !(S::load(ar[i]) <= 0) ? S::load(hr[i]) : Acc(0);
      hr[i] = S::store(value);
      v[i] = value;
    }
    if (pgb) {
#pragma omp simd
      for (int64_t i = 0; i < hidden; ++i) pgb[i] += v[i];
    }
    // The gradient of the product that made this layer from its input rows x, kept as
    // (inputs x hidden): x's zeros (a one-hot block) are skipped.
    for (int64_t c = 0; c < inputs; ++c) {
      Acc xc = S::load(px[r * inputs + c]);
      if (xc == 0) continue;
      Acc* out = pgx + c * hidden;
#pragma omp simd
      for (int64_t i = 0; i < hidden; ++i) out[i] += xc * v[i];
    }
  }
}


#ifdef NEURAL_BTF_AVX512
// The same kernels on 16 lanes of AVX-512, for float32 and (where the CPU has AVX512_BF16)
// bfloat16 storage, float32 sums: a row of 106 is 6 full vectors and a masked one. GCC's
// own vectorization of the loops above was slow on bfloat16 rows (its rounding and 8-lane
// vectors; docs/performance.md).
#ifdef NEURAL_BTF_AVX512_BF16
struct VecBFloat16 {
  using Raw = uint16_t;
  static __m512 load(const uint16_t* p, __mmask16 m) {
    __m256i bits = _mm256_maskz_loadu_epi16(m, p);
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(bits), 16));
  }
  static __m256i pack(__m512 v) { return (__m256i)_mm512_cvtneps_pbh(v); }  // nearest, even
  static void store(uint16_t* p, __mmask16 m, __m512 v) { _mm256_mask_storeu_epi16(p, m, pack(v)); }
  static __m512 round(__m512 v) {
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(pack(v)), 16));
  }
};
#endif

struct VecFloat {
  using Raw = float;
  static __m512 load(const float* p, __mmask16 m) { return _mm512_maskz_loadu_ps(m, p); }
  static void store(float* p, __mmask16 m, __m512 v) { _mm512_mask_storeu_ps(p, m, v); }
  static __m512 round(__m512 v) { return v; }
};

inline __mmask16 lanes(int64_t i, int64_t n) {
  int64_t left = n - i;
  return left >= 16 ? __mmask16(0xFFFF) : __mmask16((1u << left) - 1u);
}

// dst[0, n) += the n lanes of the vectors src[0, ceil(n / 16)).
inline void add_into(float* dst, const __m512* src, int64_t n) {
  for (int64_t k = 0; 16 * k < n; ++k) {
    __mmask16 m = lanes(16 * k, n);
    _mm512_mask_storeu_ps(dst + 16 * k, m,
                          _mm512_add_ps(_mm512_maskz_loadu_ps(m, dst + 16 * k), src[k]));
  }
}

template <typename V>
void output_layer_avx512(int64_t rows, int64_t hidden, const at::Tensor& a, const at::Tensor& w,
                         const at::Tensor& b, const at::Tensor& targets, double scale,
                         const at::Tensor& g, const at::Tensor& g_w, const at::Tensor& g_b,
                         const at::Tensor& g_b_hidden, const at::Tensor& loss) {
  constexpr int O = 3;
  const int64_t blocks = (hidden + 15) / 16;
  const auto* pa = reinterpret_cast<const typename V::Raw*>(a.const_data_ptr());
  const auto* pw = reinterpret_cast<const typename V::Raw*>(w.const_data_ptr());
  const auto* pb = reinterpret_cast<const typename V::Raw*>(b.const_data_ptr());
  auto* pg = reinterpret_cast<typename V::Raw*>(g.mutable_data_ptr());
  const float* pt = targets.const_data_ptr<float>();
  float* pgw = g_w.mutable_data_ptr<float>();
  float* pgb = g_b.mutable_data_ptr<float>();
  float* pgh = g_b_hidden.mutable_data_ptr<float>();
  // Weights and gradient sums as whole vectors, zero-padded to 16 lanes.
  std::vector<__m512> wv(O * blocks), gwv(O * blocks, _mm512_setzero_ps());
  std::vector<__m512> ghv(blocks, _mm512_setzero_ps());
  for (int j = 0; j < O; ++j)
    for (int64_t k = 0; k < blocks; ++k)
      wv[j * blocks + k] = V::load(pw + j * hidden + 16 * k, lanes(16 * k, hidden));
  float bias[O], gbs[O] = {0, 0, 0};
  for (int j = 0; j < O; ++j) {
    __m512 v = V::load(pb + j, 1);
    bias[j] = _mm512_cvtss_f32(v);
  }
  double sum_squares = 0;
  // Two rows at a time, whose dot products are independent chains the core overlaps, and
  // the gradient sums loaded once for both (faster than one row at a time; 4 or 8 rows
  // were no faster than 2: docs/performance.md).
  std::vector<__m512> av(2 * blocks);
  auto rows_at = [&]<int N>(int64_t r) {
    __m512 s[N][O];
    for (int n = 0; n < N; ++n)
      for (int j = 0; j < O; ++j) s[n][j] = _mm512_setzero_ps();
    for (int64_t k = 0; k < blocks; ++k) {
      __mmask16 m = lanes(16 * k, hidden);
      for (int n = 0; n < N; ++n) {
        __m512 x = V::load(pa + (r + n) * hidden + 16 * k, m);
        av[n * blocks + k] = x;
        for (int j = 0; j < O; ++j) s[n][j] = _mm512_fmadd_ps(x, wv[j * blocks + k], s[n][j]);
      }
    }
    __m512 gj[N][O];
    for (int n = 0; n < N; ++n) {
      for (int j = 0; j < O; ++j) {
        __m512 out = V::round(_mm512_set1_ps(_mm512_reduce_add_ps(s[n][j]) + bias[j]));
        float residual = _mm512_cvtss_f32(out) - pt[(r + n) * O + j];
        sum_squares += double(residual) * double(residual);
        gj[n][j] = V::round(_mm512_set1_ps(residual * float(scale)));
        gbs[j] += _mm512_cvtss_f32(gj[n][j]);
      }
    }
    // Each vector of weights and of gradient sums is loaded once for the N rows.
    for (int64_t k = 0; k < blocks; ++k) {
      const __mmask16 m = lanes(16 * k, hidden);
      __m512 wk[O], gw[O];
      for (int j = 0; j < O; ++j) {
        wk[j] = wv[j * blocks + k];
        gw[j] = gwv[j * blocks + k];
      }
      __m512 gh = ghv[k];
      for (int n = 0; n < N; ++n) {
        const __m512 x = av[n * blocks + k];
        __m512 h = _mm512_mul_ps(gj[n][0], wk[0]);
        for (int j = 1; j < O; ++j) h = _mm512_fmadd_ps(gj[n][j], wk[j], h);
        for (int j = 0; j < O; ++j) gw[j] = _mm512_fmadd_ps(gj[n][j], x, gw[j]);
        __mmask16 positive = _mm512_cmp_ps_mask(x, _mm512_setzero_ps(), _CMP_NLE_UQ);
        h = _mm512_maskz_mov_ps(positive, V::round(h));
        V::store(pg + (r + n) * hidden + 16 * k, m, h);
        gh = _mm512_add_ps(gh, h);
      }
      for (int j = 0; j < O; ++j) gwv[j * blocks + k] = gw[j];
      ghv[k] = gh;
    }
  };
  int64_t r = 0;
  for (; r + 2 <= rows; r += 2) rows_at.template operator()<2>(r);
  for (; r < rows; ++r) rows_at.template operator()<1>(r);
  for (int j = 0; j < O; ++j) {
    pgb[j] += gbs[j];
    add_into(pgw + j * hidden, gwv.data() + j * blocks, hidden);
  }
  add_into(pgh, ghv.data(), hidden);
  *loss.mutable_data_ptr<double>() += sum_squares;
}

template <typename V>
void relu_backward_avx512(int64_t rows, int64_t hidden, const at::Tensor& h, const at::Tensor& a,
                          const c10::optional<at::Tensor>& g_b, const c10::optional<at::Tensor>& x,
                          const c10::optional<at::Tensor>& g_x) {
  const int64_t blocks = (hidden + 15) / 16;
  auto* ph = reinterpret_cast<typename V::Raw*>(h.mutable_data_ptr());
  const auto* pa = reinterpret_cast<const typename V::Raw*>(a.const_data_ptr());
  const auto* px = x ? reinterpret_cast<const typename V::Raw*>(x->const_data_ptr()) : nullptr;
  const int64_t inputs = x ? x->size(1) : 0;
  std::vector<__m512> gbv(blocks, _mm512_setzero_ps());
  std::vector<__m512> gxv(inputs * blocks, _mm512_setzero_ps());
  std::vector<__m512> v(blocks);
  std::vector<float> xr(inputs + 16);  // a row of x, padded to whole vectors
  for (int64_t r = 0; r < rows; ++r) {
    auto* hr = ph + r * hidden;
    const auto* ar = pa + r * hidden;
    for (int64_t k = 0; k < blocks; ++k) {
      __mmask16 m = lanes(16 * k, hidden);
      __mmask16 positive =
          _mm512_cmp_ps_mask(V::load(ar + 16 * k, m), _mm512_setzero_ps(), _CMP_NLE_UQ);
      v[k] = _mm512_maskz_mov_ps(positive, V::load(hr + 16 * k, m));
      V::store(hr + 16 * k, m, v[k]);
      gbv[k] = _mm512_add_ps(gbv[k], v[k]);
    }
    if (inputs) {
      for (int64_t c = 0; c < inputs; c += 16)
        _mm512_storeu_ps(xr.data() + c, V::load(px + r * inputs + c, lanes(c, inputs)));
      for (int64_t c = 0; c < inputs; ++c) {
        if (xr[c] == 0) continue;  // a one-hot block's zeros
        __m512 xc = _mm512_set1_ps(xr[c]);
        for (int64_t k = 0; k < blocks; ++k)
          gxv[c * blocks + k] = _mm512_fmadd_ps(xc, v[k], gxv[c * blocks + k]);
      }
    }
  }
  if (g_b) add_into(g_b->mutable_data_ptr<float>(), gbv.data(), hidden);
  for (int64_t c = 0; c < inputs; ++c)
    add_into(g_x->mutable_data_ptr<float>() + c * hidden, gxv.data() + c * blocks, hidden);
}
#endif

void check(bool ok, const char* what) { TORCH_CHECK(ok, "neural_btf kernels: ", what); }

// run(storage) with the storage policy of a tensor type.
template <typename F>
void dispatch(at::ScalarType type, const char* op, F&& run) {
  if (type == at::kBFloat16) {
    run(BFloat16{});
  } else if (type == at::kFloat) {
    run(Plain<float>{});
  } else if (type == at::kDouble) {
    run(Plain<double>{});
  } else {
    TORCH_CHECK(false, "neural_btf kernels: ", op, ": bfloat16, float32 or float64 only");
  }
}

at::Tensor output_layer(const at::Tensor& a, const at::Tensor& w, const at::Tensor& b,
                        const at::Tensor& targets, double scale, const at::Tensor& g_w,
                        const at::Tensor& g_b, const at::Tensor& g_b_hidden,
                        const at::Tensor& loss) {
  check(a.is_cpu() && w.is_cpu() && targets.is_cpu(), "output_layer runs on the CPU only");
  check(a.dim() == 2 && a.is_contiguous() && w.is_contiguous() && targets.is_contiguous() &&
            b.is_contiguous() && g_b.is_contiguous() && g_b_hidden.is_contiguous(),
        "output_layer wants contiguous 2-D activations, weights and targets");
  const int64_t rows = a.size(0), hidden = a.size(1), outputs = w.size(0);
  check(w.size(1) == hidden && b.numel() == outputs && targets.size(0) == rows &&
            targets.size(1) == outputs,
        "output_layer: shapes do not match");
  check(w.scalar_type() == a.scalar_type() && b.scalar_type() == a.scalar_type(),
        "output_layer: weights and activations differ in type");
  check(loss.scalar_type() == at::kDouble, "output_layer: the loss is float64");
  auto g = at::empty_like(a);
  auto run = [&](auto storage) {
    using S = decltype(storage);
    using Acc = typename S::Acc;
    check(targets.scalar_type() == c10::CppTypeToScalarType<Acc>::value &&
              g_w.scalar_type() == targets.scalar_type() &&
              g_b.scalar_type() == targets.scalar_type() &&
              g_b_hidden.scalar_type() == targets.scalar_type() && g_w.is_contiguous() &&
              g_w.size(0) == outputs && g_w.size(1) == hidden && g_b.numel() == outputs &&
              g_b_hidden.numel() == hidden,
          "output_layer: targets and gradient sums must be in the accumulator type and "
          "shaped like the weights, biases and hidden layer");
    check(outputs == 3, "output_layer: 3 outputs (RGB) only");
#ifdef NEURAL_BTF_AVX512_BF16
    if constexpr (std::is_same_v<S, BFloat16>) {
      return output_layer_avx512<VecBFloat16>(rows, hidden, a, w, b, targets, scale, g, g_w,
                                              g_b, g_b_hidden, loss);
    }
#endif
#ifdef NEURAL_BTF_AVX512
    if constexpr (std::is_same_v<S, Plain<float>>) {
      return output_layer_avx512<VecFloat>(rows, hidden, a, w, b, targets, scale, g, g_w, g_b,
                                           g_b_hidden, loss);
    }
#endif
    output_layer_kernel<S, 3>(rows, hidden, a, w, b, targets, scale, g, g_w, g_b, g_b_hidden,
                              loss);
  };
  dispatch(a.scalar_type(), "output_layer", run);
  return g;
}

void relu_backward_(const at::Tensor& h, const at::Tensor& a, const c10::optional<at::Tensor>& g_b,
                    const c10::optional<at::Tensor>& x, const c10::optional<at::Tensor>& g_x) {
  check(h.is_cpu() && a.is_cpu(), "relu_backward_ runs on the CPU only");
  check(h.dim() == 2 && h.is_contiguous() && a.is_contiguous() && h.sizes() == a.sizes() &&
            h.scalar_type() == a.scalar_type(),
        "relu_backward_ wants contiguous gradients and activations of one shape and type");
  check(x.has_value() == g_x.has_value(), "relu_backward_: x and g_x go together");
  const auto sums = h.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  check((!g_b || (g_b->scalar_type() == sums && g_b->numel() == h.size(1) &&
                  g_b->is_contiguous())) &&
            (!g_x || g_x->scalar_type() == sums),
        "relu_backward_: g_b (hidden) and g_x must be in the accumulator type");
  if (x) {
    check(x->is_contiguous() && x->size(0) == h.size(0) && x->scalar_type() == h.scalar_type() &&
              g_x->size(0) == x->size(1) && g_x->size(1) == h.size(1) && g_x->is_contiguous(),
          "relu_backward_: x (rows x inputs) and g_x (inputs x hidden) do not match");
  }
  auto run = [&](auto storage) {
    using S = decltype(storage);
#ifdef NEURAL_BTF_AVX512_BF16
    if constexpr (std::is_same_v<S, BFloat16>) {
      return relu_backward_avx512<VecBFloat16>(h.size(0), h.size(1), h, a, g_b, x, g_x);
    }
#endif
#ifdef NEURAL_BTF_AVX512
    if constexpr (std::is_same_v<S, Plain<float>>) {
      return relu_backward_avx512<VecFloat>(h.size(0), h.size(1), h, a, g_b, x, g_x);
    }
#endif
    relu_backward_kernel<S>(h.size(0), h.size(1), h, a, g_b, x, g_x);
  };
  dispatch(h.scalar_type(), "relu_backward_", run);
}

}  // namespace

TORCH_LIBRARY(NEURAL_BTF_NAMESPACE, m) {
  m.def(
      "output_layer(Tensor a, Tensor w, Tensor b, Tensor targets, float scale, Tensor(a!) g_w, "
      "Tensor(b!) g_b, Tensor(c!) g_b_hidden, Tensor(d!) loss) -> Tensor",
      &output_layer);
  m.def(
      "relu_backward_(Tensor(a!) h, Tensor a, Tensor(b!)? g_b, Tensor? x, Tensor(c!)? g_x) -> ()",
      &relu_backward_);
}
