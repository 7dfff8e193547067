// A CPU allocator that keeps freed large blocks for reuse by the next allocation of the same size.
//
// A training step of a spiking plastic policy allocates the same few hundred large tensors (traces, (batch, T, n)
// activations, their gradients) in every BPTT step and frees them after the backward pass. glibc's malloc serves
// each by searching and splitting its bins and coalesces them again on free; on the paper network that search was
// ~5 % of the main thread's time, on the training step's critical path. Here a freed block of at least
// `min_bytes` goes to a list of free blocks of its exact size, and the next allocation of that size takes it back
// in O(1); smaller blocks, and any block that would take the cached total past `max_cached_bytes`, go back to
// c10::free_cpu. Every block comes from c10::alloc_cpu with a header that holds its size, so that a data pointer
// alone frees it (Allocator::raw_allocate and raw_deleter, which some ATen kernels use, need that). The sizes
// repeat from step to step, so after the first step nearly every large allocation is a cache hit. Unlike c10's
// default allocator it reports nothing to torch.profiler's memory profiling.
//
// The cache is torch's CPU allocator only between cache_cpu_blocks() and uncache_cpu_blocks() (a spiking model's
// training): uncaching puts the allocator it replaced back and frees the cached blocks; blocks allocated through
// the cache and freed later go straight back to c10::free_cpu.

#include <c10/core/Allocator.h>
#include <c10/core/CPUAllocator.h>
#include <c10/core/impl/alloc_cpu.h>
#include <torch/library.h>

#include <cstdint>
#include <mutex>
#include <unordered_map>
#include <vector>

namespace {

class BlockCacheAllocator final : public c10::Allocator {
 public:
  // Starts caching freed blocks of at least min_bytes, up to max_cached_bytes in all.
  void activate(size_t min_bytes, size_t max_cached_bytes) {
    const std::lock_guard<std::mutex> lock(mutex_);
    min_bytes_ = min_bytes;
    max_cached_bytes_ = max_cached_bytes;
    active_ = true;
  }

  // Frees every cached block; blocks freed from now on go back to c10::free_cpu.
  void deactivate() {
    std::unordered_map<size_t, std::vector<void*>> cached;
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      active_ = false;
      cached.swap(free_);
      cached_bytes_ = 0;
    }
    for (auto& entry : cached) {
      for (void* data : entry.second) c10::free_cpu(static_cast<char*>(data) - kHeader);
    }
  }

  bool active() {
    const std::lock_guard<std::mutex> lock(mutex_);
    return active_;
  }

  // The allocator that was torch's CPU allocator before this one, put back by uncache_cpu_blocks.
  c10::Allocator* previous = nullptr;

  c10::DataPtr allocate(size_t n) override {
    void* data = nullptr;
    if (n >= min_bytes_) {
      const std::lock_guard<std::mutex> lock(mutex_);
      auto it = free_.find(n);
      if (it != free_.end() && !it->second.empty()) {
        data = it->second.back();
        it->second.pop_back();
        cached_bytes_ -= n;
      }
    }
    if (data == nullptr) {
      char* base = static_cast<char*>(c10::alloc_cpu(n + kHeader));
      *reinterpret_cast<size_t*>(base) = n;
      data = base + kHeader;
    }
    // The context is the data pointer itself (raw_allocate, which some ATen kernels use, requires it).
    return {data, data, &release, c10::Device(c10::DeviceType::CPU)};
  }

  c10::DeleterFnPtr raw_deleter() const override { return &release; }

  void copy_data(void* dest, const void* src, std::size_t count) const override {
    default_copy_data(dest, src, count);
  }

  size_t cached_bytes() {
    const std::lock_guard<std::mutex> lock(mutex_);
    return cached_bytes_;
  }

  static BlockCacheAllocator* instance;

 private:
  // Each block starts with a header that holds its size, one alignment unit long so that the data stays aligned
  // as c10::alloc_cpu aligns it.
  static constexpr size_t kHeader = 64;

  static void release(void* data) { instance->give_back(data); }

  void give_back(void* data) {
    char* base = static_cast<char*>(data) - kHeader;
    const size_t n = *reinterpret_cast<size_t*>(base);
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      if (active_ && n >= min_bytes_ && cached_bytes_ + n <= max_cached_bytes_) {
        free_[n].push_back(data);
        cached_bytes_ += n;
        return;
      }
    }
    c10::free_cpu(base);
  }

  size_t min_bytes_ = 0, max_cached_bytes_ = 0;
  bool active_ = false;
  std::mutex mutex_;
  std::unordered_map<size_t, std::vector<void*>> free_;
  size_t cached_bytes_ = 0;
};

BlockCacheAllocator* BlockCacheAllocator::instance = nullptr;

std::mutex install_mutex;

// Makes the cache torch's CPU allocator (created on the first call, never deleted: tensors allocated through it may
// outlive any owner); returns whether this call installed it (false: it already was).
bool cache_cpu_blocks(int64_t min_bytes, int64_t max_cached_bytes) {
  const std::lock_guard<std::mutex> lock(install_mutex);
  TORCH_CHECK(min_bytes > 0 && max_cached_bytes >= 0, "cache_cpu_blocks: min_bytes > 0 and max_cached_bytes >= 0");
  if (BlockCacheAllocator::instance == nullptr) BlockCacheAllocator::instance = new BlockCacheAllocator();
  BlockCacheAllocator* cache = BlockCacheAllocator::instance;
  if (cache->active()) return false;
  cache->previous = c10::GetCPUAllocator();
  cache->activate(static_cast<size_t>(min_bytes), static_cast<size_t>(max_cached_bytes));
  c10::SetCPUAllocator(cache, /*priority=*/10);
  return true;
}

// Puts back the allocator that cache_cpu_blocks replaced and frees the cached blocks; returns whether the cache
// was installed.
bool uncache_cpu_blocks() {
  const std::lock_guard<std::mutex> lock(install_mutex);
  BlockCacheAllocator* cache = BlockCacheAllocator::instance;
  if (cache == nullptr || !cache->active()) return false;
  c10::SetCPUAllocator(cache->previous, /*priority=*/10);
  cache->deactivate();
  return true;
}

// Whether the cache is torch's CPU allocator now.
bool cpu_block_cache_active() {
  return BlockCacheAllocator::instance != nullptr && BlockCacheAllocator::instance->active();
}

// Bytes of freed blocks the cache holds now (0 when it is not installed).
int64_t cpu_block_cache_bytes() {
  return BlockCacheAllocator::instance != nullptr ? static_cast<int64_t>(BlockCacheAllocator::instance->cached_bytes())
                                                  : 0;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(sb3_spikeplastic_fast, m) {
  m.def("cache_cpu_blocks(int min_bytes, int max_cached_bytes) -> bool", &cache_cpu_blocks);
  m.def("uncache_cpu_blocks() -> bool", &uncache_cpu_blocks);
  m.def("cpu_block_cache_active() -> bool", &cpu_block_cache_active);
  m.def("cpu_block_cache_bytes() -> int", &cpu_block_cache_bytes);
}
