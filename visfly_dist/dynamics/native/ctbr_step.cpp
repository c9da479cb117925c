// The forward of one CTBR control step (visfly_dist/dynamics/adjoint.py, CtbrStep.forward) for
// steps without gradients: clamp and set point, then per substep the CTBR inner loop, RK4 or Euler
// of the model derivative, the ground reaction; then quaternion renormalisation.
//
// NumPy runs that as ~500 small array ops per control step, and at a few hundred agents their
// dispatch, not the arithmetic, is the cost. Here agents go through in blocks of B lanes held
// component-major ([row][lane]), so every line below is a loop over the lanes that the compiler
// vectorises. The model and the inner loop are given as lists of their nonzero quadratic terms
// ``value * u[a] * u[b]`` (built from the dense matrices by visfly_dist/dynamics/native_step.py),
// so only nonzero multiply-adds run. Arithmetic is in the dtype of the arrays (float or double),
// as in the NumPy forward.
#include <cmath>
#include <cstdint>

#include "../../native_clones.h"  // VF_CLONES

namespace {

constexpr int B = 16;         // agents per block
constexpr int STATE = 17;     // pos 3, vel 3, quat 4, omega 3, rotor 4
constexpr int MODEL_U = 12;   // model terms' u: [1, rotor (4), quat (4), omega (3)]
constexpr int LOOP_U = 8;     // inner loop terms' u: [1, omega (3), rotor (4)]

// Everything is inlined into the exported functions, so each of their builds (VF_CLONES) has its own.
#define VF_INLINE inline __attribute__((always_inline))

struct Term {
    std::int32_t row, a, b;
};

// Layout shared with native_step.py (_Params); pointers to T are of the step's dtype.
struct Params {
    std::int64_t substeps, rk4, ground, motor_lag, n_terms, n_loop_terms;
    std::int64_t wind_stride;        // 0: one wind for all agents, 3: (N, 3) per agent
    const Term* terms;               // the model: y[row] += value * u[a] * u[b], y (17)
    const void* term_values;
    const Term* loop_terms;          // the inner loop: thrust[row] += value * u[a] * u[b], thrust (4)
    const void* loop_values;
    const void* constants;           // see Constants
    const void* wind;                // null: no wind
};

// ``constants`` in this order.
template <typename T>
struct Constants {
    T loop_bias[4], setpoint_matrix[16], action_scale[4];
    T drag_linear[3], drag_quadratic[3], gravity[3];
    T h, half_h, sixth_h, inv_motor_tau, half_b, half_b_squared, low, high;
};

template <typename T>
struct Model {
    const Params& p;
    const Constants<T>& c;
    const T* values;
    const T* loop_values;
    T wind[3][B];
};

// ds/dt (17 x B) with rotor commands ``cmd`` held (CtbrStep.derivative).
template <typename T>
VF_INLINE void derivative(const Model<T>& m, const T (&s)[STATE][B], const T (&cmd)[4][B], T (&out)[STATE][B]) {
    T u[MODEL_U][B], y[STATE][B];
    for (int l = 0; l < B; ++l) u[0][l] = T(1);
    for (int k = 0; k < 4; ++k)
        for (int l = 0; l < B; ++l) u[1 + k][l] = s[13 + k][l];
    for (int k = 0; k < 7; ++k)
        for (int l = 0; l < B; ++l) u[5 + k][l] = s[6 + k][l];
    for (int r = 0; r < STATE; ++r)
        for (int l = 0; l < B; ++l) y[r][l] = T(0);
    for (std::int64_t t = 0; t < m.p.n_terms; ++t) {
        const Term term = m.p.terms[t];
        const T v = m.values[t];
        for (int l = 0; l < B; ++l) y[term.row][l] += v * (u[term.a][l] * u[term.b][l]);
    }
    const Constants<T>& c = m.c;
    // y[4:13] is R row-major: R[i][j] = y[4 + 3 i + j]
    T rel[3][B], force[3][B];
    for (int i = 0; i < 3; ++i)
        for (int l = 0; l < B; ++l) rel[i][l] = s[3 + i][l] - m.wind[i][l];
    for (int j = 0; j < 3; ++j)
        for (int l = 0; l < B; ++l) {
            const T vb = y[4 + j][l] * rel[0][l] + y[7 + j][l] * rel[1][l] + y[10 + j][l] * rel[2][l];  // R^T v
            force[j][l] = vb * (c.drag_linear[j] + c.drag_quadratic[j] * std::fabs(vb));
        }
    for (int l = 0; l < B; ++l) force[2][l] += y[0][l];                                         // collective
    for (int i = 0; i < 3; ++i)
        for (int l = 0; l < B; ++l) {
            out[i][l] = s[3 + i][l];
            out[3 + i][l] = y[4 + 3 * i][l] * force[0][l] + y[5 + 3 * i][l] * force[1][l]
                            + y[6 + 3 * i][l] * force[2][l] + c.gravity[i];                  // R f + g
        }
    for (int k = 0; k < 4; ++k)
        for (int l = 0; l < B; ++l) out[6 + k][l] = y[13 + k][l];
    for (int k = 0; k < 3; ++k)
        for (int l = 0; l < B; ++l) out[10 + k][l] = y[1 + k][l];
    for (int k = 0; k < 4; ++k)
        for (int l = 0; l < B; ++l) out[13 + k][l] = (cmd[k][l] - s[13 + k][l]) * c.inv_motor_tau;
}

// Rotor commands of the CTBR inner loop (CtbrStep.command).
template <typename T>
VF_INLINE void command(const Model<T>& m, const T (&s)[STATE][B], const T (&setpoint)[4][B], T (&cmd)[4][B]) {
    T u[LOOP_U][B], thrust[4][B];
    for (int l = 0; l < B; ++l) u[0][l] = T(1);
    for (int k = 0; k < 3; ++k)
        for (int l = 0; l < B; ++l) u[1 + k][l] = s[10 + k][l];
    for (int k = 0; k < 4; ++k)
        for (int l = 0; l < B; ++l) u[4 + k][l] = s[13 + k][l];
    for (int r = 0; r < 4; ++r)
        for (int l = 0; l < B; ++l) thrust[r][l] = T(0);
    for (std::int64_t t = 0; t < m.p.n_loop_terms; ++t) {
        const Term term = m.p.loop_terms[t];
        const T v = m.loop_values[t];
        for (int l = 0; l < B; ++l) thrust[term.row][l] += v * (u[term.a][l] * u[term.b][l]);
    }
    const Constants<T>& c = m.c;
    for (int r = 0; r < 4; ++r)
        for (int l = 0; l < B; ++l) {
            T x = setpoint[r][l] + thrust[r][l];
            x = x < c.low ? c.low : (x > c.high ? c.high : x);   // keeps NaN, as np.clip
            cmd[r][l] = std::sqrt(x + c.half_b_squared) - c.half_b;
        }
}

template <typename T>
VF_INLINE void axpy(const T (&s)[STATE][B], T a, const T (&k)[STATE][B], T (&out)[STATE][B]) {
    for (int r = 0; r < STATE; ++r)
        for (int l = 0; l < B; ++l) out[r][l] = s[r][l] + a * k[r][l];
}

// One control step of a block of agents, in place on ``s``; ``contact`` gets 0 or 1 per lane.
template <typename T>
VF_INLINE void step_block(const Model<T>& m, T (&s)[STATE][B], const T (&action)[4][B], std::uint8_t (&contact)[B]) {
    const Constants<T>& c = m.c;
    T command_in[4][B], setpoint[4][B], cmd[4][B];
    for (int r = 0; r < 4; ++r)
        for (int l = 0; l < B; ++l) {
            T a = action[r][l];
            a = a < T(-1) ? T(-1) : (a > T(1) ? T(1) : a);
            command_in[r][l] = (r == 0 ? a + T(1) : a) * c.action_scale[r];
        }
    for (int r = 0; r < 4; ++r)
        for (int l = 0; l < B; ++l) {
            T acc = T(0);
            for (int j = 0; j < 4; ++j) acc += c.setpoint_matrix[4 * r + j] * command_in[j][l];
            setpoint[r][l] = c.loop_bias[r] + acc;
        }
    for (int l = 0; l < B; ++l) contact[l] = 0;
    T k1[STATE][B], k2[STATE][B], k3[STATE][B], k4[STATE][B], tmp[STATE][B];
    for (std::int64_t sub = 0; sub < m.p.substeps; ++sub) {
        command(m, s, setpoint, cmd);
        if (!m.p.motor_lag)
            for (int k = 0; k < 4; ++k)
                for (int l = 0; l < B; ++l) s[13 + k][l] = cmd[k][l];
        derivative(m, s, cmd, k1);
        if (m.p.rk4) {
            axpy(s, c.half_h, k1, tmp);
            derivative(m, tmp, cmd, k2);
            axpy(s, c.half_h, k2, tmp);
            derivative(m, tmp, cmd, k3);
            axpy(s, c.h, k3, tmp);
            derivative(m, tmp, cmd, k4);
            for (int r = 0; r < STATE; ++r)
                for (int l = 0; l < B; ++l)
                    s[r][l] = s[r][l] + c.sixth_h * (k1[r][l] + T(2) * (k2[r][l] + k3[r][l]) + k4[r][l]);
        } else {
            for (int r = 0; r < STATE; ++r)
                for (int l = 0; l < B; ++l) s[r][l] = s[r][l] + c.h * k1[r][l];
        }
        for (int l = 0; l < B; ++l) {
            const T z = s[2][l], vz = s[5][l];
            contact[l] |= static_cast<std::uint8_t>(z <= T(0));
            if (m.p.ground) {
                s[2][l] = z < T(0) ? T(0) : z;                       // keeps NaN, as np.maximum
                s[5][l] = z < T(0) ? (vz < T(0) ? T(0) : vz) : vz;
            }
        }
    }
    for (int l = 0; l < B; ++l) {
        const T norm = std::sqrt(s[6][l] * s[6][l] + s[7][l] * s[7][l] + s[8][l] * s[8][l] + s[9][l] * s[9][l]);
        for (int k = 0; k < 4; ++k) s[6 + k][l] /= norm;
    }
}

constexpr int WIDTHS[6] = {3, 3, 4, 3, 4, 4};     // pos, vel, quat, omega, rotor, action
constexpr int OFFSETS[6] = {0, 3, 6, 10, 13, 0};

template <typename T>
VF_INLINE void step(const Params& p, const void* const* inputs, const std::int64_t* strides, void* const* outputs,
          std::uint8_t* contact, std::int64_t n) {
    Model<T> m{p, *static_cast<const Constants<T>*>(p.constants), static_cast<const T*>(p.term_values),
               static_cast<const T*>(p.loop_values), {}};
    const T* wind = static_cast<const T*>(p.wind);
    for (std::int64_t first = 0; first < n; first += B) {
        T s[STATE][B], action[4][B];
        std::uint8_t hit[B];
        for (int l = 0; l < B; ++l) {
            // lanes past the last agent repeat the block's first agent (computed, never written)
            const std::int64_t agent = first + l < n ? first + l : first;
            for (int c = 0; c < 6; ++c) {
                const T* row = static_cast<const T*>(inputs[c]) + agent * strides[c];
                for (int j = 0; j < WIDTHS[c]; ++j) {
                    if (c == 5)
                        action[j][l] = row[j];
                    else
                        s[OFFSETS[c] + j][l] = row[j];
                }
            }
            for (int i = 0; i < 3; ++i) m.wind[i][l] = wind == nullptr ? T(0) : wind[agent * p.wind_stride + i];
        }
        step_block(m, s, action, hit);
        for (int l = 0; l < B && first + l < n; ++l) {
            for (int c = 0; c < 5; ++c) {
                T* row = static_cast<T*>(outputs[c]) + (first + l) * WIDTHS[c];
                for (int j = 0; j < WIDTHS[c]; ++j) row[j] = s[OFFSETS[c] + j][l];
            }
            contact[first + l] = hit[l];
        }
    }
}

}  // namespace


extern "C" {

int vf_dynamics_version() { return 1; }

// One control step of ``n`` agents. ``inputs``: pos, vel, quat, omega, rotor, action, batch-first
// rows of the step's dtype with ``strides[i]`` elements between agents (0: one row for all);
// ``outputs``: the next pos, vel, quat, omega, rotor, contiguous (n, width); ``contact``: n bytes,
// 1 where z <= 0 after a substep.
VF_CLONES void vf_ctbr_step_f32(const Params* p, const void* const* inputs, const std::int64_t* strides,
                      void* const* outputs, std::uint8_t* contact, std::int64_t n) {
    step<float>(*p, inputs, strides, outputs, contact, n);
}

VF_CLONES void vf_ctbr_step_f64(const Params* p, const void* const* inputs, const std::int64_t* strides,
                      void* const* outputs, std::uint8_t* contact, std::int64_t n) {
    step<double>(*p, inputs, strides, outputs, contact, n);
}

}  // extern "C"
