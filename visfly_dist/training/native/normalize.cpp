// VecNormalize's running statistics and scaling of one step (tensor_ppo.Normalizer) in one call each:
// the observations' and the rewards'.
//
// In torch each is about twenty small operations (a float64 var_mean, Chan's update, the scaling,
// the clip, the casts), and at a few hundred agents their dispatch, not the arithmetic, is the cost.
// Each line keeps the torch code's operations, their order and their dtypes (no fast-math, no
// contraction: see the Makefile), so the update agrees with RunningMoments.update up to the rounding
// of the batch moments (two passes here, Welford's in torch) and the scaled values are torch's, cast
// to float32 as torch casts them.
#include <cmath>
#include <cstdint>
#include <vector>

#include "../../native_clones.h"  // VF_CLONES

namespace {

#define VF_INLINE inline __attribute__((always_inline))

// torch's clamp(lo, hi): NaN stays NaN.
template <typename T>
VF_INLINE T clamp(T x, T lo, T hi) { return x < lo ? lo : (x > hi ? hi : x); }

// RunningMoments.update after its batch moments: Chan et al.'s parallel update of width columns,
// each product and sum in the order the torch code writes them. new_mean/new_var hold the batch's
// mean and variance on entry and the updated statistics on return.
VF_INLINE void chan_update(const double* mean, const double* var, double* new_mean, double* new_var,
                           std::int64_t width, double count, std::int64_t rows) {
    const double n = static_cast<double>(rows);
    const double total = count + n;
    const double step = n / total;               // n / total
    const double spread = count * n / total;     // self.count * n / total
    for (std::int64_t j = 0; j < width; ++j) {
        const double delta = new_mean[j] - mean[j];
        const double batch_var = new_var[j];
        new_mean[j] = mean[j] + delta * step;
        new_var[j] = (var[j] * count + batch_var * n + delta * delta * spread) / total;
    }
}

}  // namespace


extern "C" {

// Normalizer.observe on rows agents. inputs/outputs: entries contiguous float32 blocks of rows x
// widths[e] (an entry's columns of the joint row, in order). mean/var: the statistics (float64, as
// many as the widths' sum). With new_mean and new_var (not null) the rows are first added to them
// (population moments, then Chan's update from count) and the outputs scaled by the result;
// otherwise by mean/var. Each output: clamp((x - mean) / sqrt(var + epsilon), -clip, clip) in
// float64, rounded to float32.
VF_CLONES void vf_normalize_obs_f32(const float* const* inputs, float* const* outputs, const std::int64_t* widths,
                                    std::int64_t entries, std::int64_t rows, const double* mean, const double* var,
                                    double* new_mean, double* new_var, double count, double epsilon, double clip) {
    std::int64_t columns = 0;
    for (std::int64_t e = 0; e < entries; ++e) columns += widths[e];
    if (new_mean != nullptr && rows > 0) {
        const double n = static_cast<double>(rows);
        for (std::int64_t c = 0; c < columns; ++c) new_mean[c] = new_var[c] = 0.0;
        for (std::int64_t e = 0, at = 0; e < entries; at += widths[e], ++e) {
            const std::int64_t w = widths[e];
            double* sum = new_mean + at;
            for (std::int64_t i = 0; i < rows; ++i) {
                const float* x = inputs[e] + i * w;
                for (std::int64_t j = 0; j < w; ++j) sum[j] += static_cast<double>(x[j]);
            }
            for (std::int64_t j = 0; j < w; ++j) sum[j] /= n;
            double* square = new_var + at;
            for (std::int64_t i = 0; i < rows; ++i) {
                const float* x = inputs[e] + i * w;
                for (std::int64_t j = 0; j < w; ++j) {
                    const double d = static_cast<double>(x[j]) - sum[j];
                    square[j] += d * d;
                }
            }
            for (std::int64_t j = 0; j < w; ++j) square[j] /= n;
        }
        chan_update(mean, var, new_mean, new_var, columns, count, rows);
        mean = new_mean;
        var = new_var;
    }
    std::vector<double> scale(static_cast<std::size_t>(columns));
    for (std::int64_t c = 0; c < columns; ++c) scale[c] = std::sqrt(var[c] + epsilon);
    for (std::int64_t e = 0, at = 0; e < entries; at += widths[e], ++e) {
        const std::int64_t w = widths[e];
        const double* m = mean + at;
        const double* s = scale.data() + at;
        for (std::int64_t i = 0; i < rows; ++i) {
            const float* x = inputs[e] + i * w;
            float* y = outputs[e] + i * w;
            for (std::int64_t j = 0; j < w; ++j) {
                y[j] = static_cast<float>(clamp((static_cast<double>(x[j]) - m[j]) / s[j], -clip, clip));
            }
        }
    }
}

// Normalizer.reward on all rows agents (none held). returns: their discounted returns (float64);
// new_returns gets returns * gamma + reward, restarted (0) where done. mean/var: the returns'
// statistics (float64 scalars), updated into new_mean/new_var with the rows' new returns from count.
// out: clamp(reward / float(sqrt(var + epsilon)), -clip, clip) in float32 with the updated var.
VF_CLONES void vf_normalize_reward_f32(const float* reward, const bool* done, const double* returns,
                                       double* new_returns, std::int64_t rows, double gamma, const double* mean,
                                       const double* var, double* new_mean, double* new_var, double count,
                                       double epsilon, float clip, float* out) {
    if (rows <= 0) return;
    const double n = static_cast<double>(rows);
    double sum = 0.0;
    for (std::int64_t i = 0; i < rows; ++i) {
        new_returns[i] = returns[i] * gamma + static_cast<double>(reward[i]);
        sum += new_returns[i];
    }
    double batch_mean = sum / n, batch_var = 0.0;
    for (std::int64_t i = 0; i < rows; ++i) {
        const double d = new_returns[i] - batch_mean;
        batch_var += d * d;
    }
    batch_var /= n;
    chan_update(mean, var, &batch_mean, &batch_var, 1, count, rows);
    *new_mean = batch_mean;
    *new_var = batch_var;
    const float scale = static_cast<float>(std::sqrt(batch_var + epsilon));
    for (std::int64_t i = 0; i < rows; ++i) {
        out[i] = clamp(reward[i] / scale, -clip, clip);
        if (done[i]) new_returns[i] = 0.0;
    }
}

}  // extern "C"
