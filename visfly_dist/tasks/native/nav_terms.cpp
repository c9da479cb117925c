// The navigation task's per-step terms without gradients (visfly_dist/tasks/navigation.py): the goal
// geometry of _GoalGeometry and the "ours" reward of NavigationEnv.get_reward.
//
// In torch each term is a few dozen operations on (N,) and (N, 3) tensors, and at a few hundred
// agents their dispatch, not the arithmetic, is the cost. Here one call runs every agent through
// plain float32 loops. Each line keeps the torch code's operations and their order (no fast-math,
// no contraction: see the Makefile), the norms' fused multiply-adds included where torch's CPU
// kernels use them (``fused``), so the geometry agrees bit for bit and the reward up to the float32
// rounding of its weighted sum (a BLAS product in torch).
#include <cmath>
#include <cstdint>

#include "../../native_clones.h"  // VF_CLONES

namespace {

// Inlined into the exported functions, so each of their builds (VF_CLONES) has its own.
#define VF_INLINE inline __attribute__((always_inline))

// Row-major rotation matrix entry k is (q[LEFT[k]] * (q[RIGHT[k]] * COEF[k]) +
// q[LEFT[9 + k]] * (q[RIGHT[9 + k]] * COEF[9 + k])) + EYE[k]: rotations.rotmat_rows, term for term.
constexpr int W = 0, X = 1, Y = 2, Z = 3;
constexpr int LEFT[18] = {Y, X, X, X, X, Y, X, Y, X, Z, W, W, W, Z, W, W, W, Y};
constexpr int RIGHT[18] = {Y, Y, Z, Y, X, Z, Z, Z, X, Z, Z, Y, Z, Z, X, Y, X, Y};
constexpr float COEF[18] = {-2, 2, 2, 2, -2, 2, 2, 2, -2, -2, -2, 2, 2, -2, -2, -2, 2, -2};
constexpr float EYE[9] = {1.0f, -0.0f, -0.0f, -0.0f, 1.0f, -0.0f, -0.0f, -0.0f, 1.0f};

// torch.linalg.vector_norm of a 3-vector on the CPU: the first square, then multiply-adds, fused
// where torch's vectorised kernels fuse them (every capability but DEFAULT).
VF_INLINE float norm3(const float* v, bool fused) {
    float acc = v[0] * v[0];
    for (int k = 1; k < 3; ++k) {
        acc = fused ? std::fma(v[k], v[k], acc) : acc + v[k] * v[k];
    }
    return std::sqrt(acc);
}

// torch's clamp(min=lo): NaN stays NaN.
VF_INLINE float clamp_min(float x, float lo) { return x < lo ? lo : x; }

enum GeometryInput { G_POS, G_VEL, G_QUAT, G_OMEGA, G_GOAL, G_INPUTS };

enum RewardInput {
    R_POS, R_VEL, R_NEAREST, R_OBSTACLE_DISTANCE, R_PREV_DISTANCE, R_DISTANCE, R_HEADING, R_SPEED, R_SPIN,
    R_SUCCESS, R_FAILURE, R_INPUTS
};

// Layout shared with native_terms.py (_RewardParams): the comparison bounds, the control step, the
// weights of (speed, spin, proximity, progress, heading, approach, success, failure).
struct RewardParams {
    float seen_below, near, dt;
    float weights[8];
    std::int64_t fused;  // torch's norms fuse their multiply-adds
};

}  // namespace


extern "C" {

int vf_tasks_version() { return 1; }

// _GoalGeometry of n agents. inputs: pos (3), vel (3), quat (4), omega (3), goal (3) rows of floats
// at the row strides ``strides`` (elements). terms: (4, n) rows distance, heading, speed, spin;
// target: (n, 4) the goal's direction in the body frame, then its distance. fused: as torch's norms.
VF_CLONES void vf_nav_geometry_f32(const float* const* inputs, const std::int64_t* strides, float* terms,
                                   float* target, std::int64_t n, std::int64_t fused) {
    for (std::int64_t i = 0; i < n; ++i) {
        const float* pos = inputs[G_POS] + i * strides[G_POS];
        const float* q = inputs[G_QUAT] + i * strides[G_QUAT];
        const float* goal = inputs[G_GOAL] + i * strides[G_GOAL];
        const float offset[3] = {goal[0] - pos[0], goal[1] - pos[1], goal[2] - pos[2]};
        const float distance = norm3(offset, fused);
        const float clamped = clamp_min(distance, 1e-6f);
        const float direction[3] = {offset[0] / clamped, offset[1] / clamped, offset[2] / clamped};
        float r[9];
        for (int k = 0; k < 9; ++k) {
            const float a = q[LEFT[k]] * (q[RIGHT[k]] * COEF[k]);
            const float b = q[LEFT[9 + k]] * (q[RIGHT[9 + k]] * COEF[9 + k]);
            r[k] = (a + b) + EYE[k];
        }
        float* t = target + 4 * i;
        for (int j = 0; j < 3; ++j) {  // (R^T d)_j = sum_k R_kj d_k
            const float a = r[j] * direction[0];
            const float b = r[3 + j] * direction[1];
            const float c = r[6 + j] * direction[2];
            t[j] = ((0.0f + a) + b) + c;  // torch's sum starts from +0: -0 terms sum to +0
        }
        t[3] = distance;
        terms[i] = distance;
        terms[n + i] = t[0];
        terms[2 * n + i] = norm3(inputs[G_VEL] + i * strides[G_VEL], fused);
        terms[3 * n + i] = norm3(inputs[G_OMEGA] + i * strides[G_OMEGA], fused);
    }
}

// NavigationEnv.get_reward with reward="ours" of n agents: obstacle_terms, progress_speed and the
// weighted sum. inputs (strides in elements): pos, vel, nearest (rows of 3 floats), then the (n,)
// obstacle distance, previous and current goal distance, heading, speed, spin (floats), success,
// failure (bytes 0 or 1). out: (n,).
VF_CLONES void vf_nav_reward_f32(const void* const* inputs, const std::int64_t* strides, const RewardParams* p,
                                 float* out, std::int64_t n) {
    const auto row = [&](int k, std::int64_t i) {
        return static_cast<const float*>(inputs[k]) + i * strides[k];
    };
    const auto value = [&](int k, std::int64_t i) { return *row(k, i); };
    const auto flag = [&](int k, std::int64_t i) {
        return static_cast<const std::uint8_t*>(inputs[k])[i * strides[k]] != 0;
    };
    for (std::int64_t i = 0; i < n; ++i) {
        const float* pos = row(R_POS, i);
        const float* vel = row(R_VEL, i);
        const float* nearest = row(R_NEAREST, i);
        const bool seen = value(R_OBSTACLE_DISTANCE, i) < p->seen_below;
        const float delta[3] = {nearest[0] - pos[0], nearest[1] - pos[1], nearest[2] - pos[2]};
        const float d = norm3(delta, p->fused);
        const float clamped = clamp_min(d, 1e-6f);
        const float a = vel[0] * (delta[0] / clamped);
        const float b = vel[1] * (delta[1] / clamped);
        const float c = vel[2] * (delta[2] / clamped);
        const float approach = clamp_min(((0.0f + a) + b) + c, 0.0f) * ((seen && d < p->near) ? 1.0f : 0.0f);
        const float proximity = (1.0f / (d + 0.2f)) * (seen ? 1.0f : 0.0f);
        const float progress = (value(R_PREV_DISTANCE, i) - value(R_DISTANCE, i)) / p->dt;
        const float terms[8] = {value(R_SPEED, i), value(R_SPIN, i), proximity, progress, value(R_HEADING, i),
                                approach, flag(R_SUCCESS, i) ? 1.0f : 0.0f, flag(R_FAILURE, i) ? 1.0f : 0.0f};
        float sum = terms[0] * p->weights[0];
        for (int k = 1; k < 8; ++k) {
            sum = sum + terms[k] * p->weights[k];
        }
        out[i] = sum;
    }
}

}  // extern "C"
