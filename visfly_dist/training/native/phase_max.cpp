// The maximum over the last axis of size 4 (the four phases of a 2x2 max-pool, see conv_pool.py),
// with the index of the first maximal entry, and its backward pass.
// PyTorch's max(dim=-1) computes int64 indices through a generic reduction; on the first layer of
// the image trunk (512 x 30 x 30 x 6 groups) that was the largest single cost of a PPO minibatch.
// Plain loops over contiguous float32 arrays; a NaN wins and stays, as in torch.max.
#include <cstdint>
#include <cstddef>

extern "C" {

int vf_kernels_version() { return 2; }

void vf_phase_max_forward(const float* y, float* out, std::uint8_t* index, std::int64_t groups) {
    for (std::int64_t g = 0; g < groups; ++g) {
        const float* v = y + 4 * g;
        float best = v[0];
        std::uint8_t at = 0;
        for (std::uint8_t k = 1; k < 4; ++k) {
            const bool nan = v[k] != v[k];
            if ((v[k] > best || nan) && best == best) {
                best = v[k];
                at = k;
            }
        }
        out[g] = best;
        index[g] = at;
    }
}

void vf_phase_max_backward(const float* grad, const std::uint8_t* index, float* grad_in, std::int64_t groups) {
    for (std::int64_t g = 0; g < groups; ++g) {
        float* dst = grad_in + 4 * g;
        const float v = grad[g];
        const std::uint8_t at = index[g];
        // branch-free: the index is random, a branch would mispredict every other group
        dst[0] = at == 0 ? v : 0.0f;
        dst[1] = at == 1 ? v : 0.0f;
        dst[2] = at == 2 ? v : 0.0f;
        dst[3] = at == 3 ? v : 0.0f;
    }
}

}  // extern "C"
