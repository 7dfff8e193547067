// torch.set_flush_denormal sets the flush-to-zero (FTZ) and denormals-are-zero (DAZ) bits of the calling thread
// only; the threads of torch's pool keep the mode they were started with. A kernel reads its caller's bits
// before a parallel region and sets them in each worker for the region's duration, so that its results (and
// its speed: subnormal arithmetic is ~100x slower) do not depend on which thread ran which part.
#pragma once

#if defined(__x86_64__) || defined(_M_X64)
#include <xmmintrin.h>

class CallerDenormalMode {
 public:
  CallerDenormalMode() : bits_(_mm_getcsr() & kBits) {}
  unsigned int bits() const { return bits_; }
  static constexpr unsigned int kBits = 0x8040;  // FTZ (bit 15) | DAZ (bit 6)

 private:
  unsigned int bits_;
};

class DenormalModeScope {
 public:
  explicit DenormalModeScope(const CallerDenormalMode& mode) : saved_(_mm_getcsr()) {
    _mm_setcsr((saved_ & ~CallerDenormalMode::kBits) | mode.bits());
  }
  ~DenormalModeScope() { _mm_setcsr(saved_); }
  DenormalModeScope(const DenormalModeScope&) = delete;
  DenormalModeScope& operator=(const DenormalModeScope&) = delete;

 private:
  unsigned int saved_;
};

#else  // other CPUs: torch.set_flush_denormal has no effect there either

class CallerDenormalMode {};

class DenormalModeScope {
 public:
  explicit DenormalModeScope(const CallerDenormalMode&) {}
};

#endif
