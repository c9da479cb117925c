// VF_CLONES: on x86-64 with GCC, a second build of a function for AVX2 and FMA (x86-64-v3), chosen
// at load time where the CPU has them; elsewhere nothing. Shared by the native libraries' kernels.
#pragma once

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VF_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define VF_CLONES
#endif
