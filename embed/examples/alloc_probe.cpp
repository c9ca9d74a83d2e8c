// occflownet-alloc-probe: counts heap allocations (malloc, calloc, realloc, memalign family, hence operator new)
// made by the whole process -- this library, onnxruntime and its threads -- during Runner::run() calls on the same
// caller-owned buffers, after a warm-up run, and the bytes they request. Usage: occflownet-alloc-probe model.onnx DIR [runs] [threads].
// DIR holds the six camera JPEG/PNGs; the model's default calibration is used. Prints one count per run.
// Counting works by interposing the allocator entry points of glibc in this executable (not in sanitizer builds).
#include "../tools/frame_io.hpp"
#include "occflownet/runner.hpp"

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
}

static std::atomic<long> g_allocs{0}, g_bytes{0};

extern "C" {
void* malloc(std::size_t n) { g_allocs.fetch_add(1, std::memory_order_relaxed); g_bytes.fetch_add(long(n)); return __libc_malloc(n); }
void* calloc(std::size_t a, std::size_t b) { g_allocs.fetch_add(1, std::memory_order_relaxed); g_bytes.fetch_add(long(a * b)); return __libc_calloc(a, b); }
void* realloc(void* p, std::size_t n) { g_allocs.fetch_add(1, std::memory_order_relaxed); g_bytes.fetch_add(long(n)); return __libc_realloc(p, n); }
void* memalign(std::size_t a, std::size_t n) { g_allocs.fetch_add(1, std::memory_order_relaxed); g_bytes.fetch_add(long(n)); return __libc_memalign(a, n); }
void* aligned_alloc(std::size_t a, std::size_t n) { return memalign(a, n); }
int posix_memalign(void** out, std::size_t a, std::size_t n) {
    void* p = memalign(a, n);
    if (!p) return 12;  // ENOMEM
    *out = p;
    return 0;
}
}

int main(int argc, char** argv) {
    if (argc < 3) {
        std::fprintf(stderr, "usage: %s model.onnx DIR [runs] [threads]\n", argv[0]);
        return 2;
    }
    try {
        occflownet::RunnerOptions options;
        options.intra_op_threads = argc > 4 ? std::atoi(argv[4]) : 0;
        occflownet::Runner runner(argv[1], options);
        const auto& info = runner.info();
        std::vector<occflownet::io::EncodedImage> images;
        for (const auto& path : occflownet::io::find_camera_images(argv[2], info.cameras))
            images.push_back(occflownet::io::probe_image(path));
        const int W = images[0].width, H = images[0].height;
        const std::size_t frame = std::size_t(W) * H * 3;
        std::vector<std::uint8_t> pixels(frame * 6), occupancy(info.grid.voxels());
        std::vector<float> density(info.grid.voxels()), K(54), T(96);
        for (std::size_t c = 0; c < 6; ++c) occflownet::io::decode_into(images[c], pixels.data() + c * frame);
        info.default_calibration.intrinsics_for_size(W, H, K.data());
        info.default_calibration.cam2ego_f32(T.data());
        const int runs = argc > 3 ? std::atoi(argv[3]) : 5;
        long before = g_allocs.load(), bytes = g_bytes.load();
        runner.run(pixels.data(), H, W, K.data(), T.data(), occupancy.data(), density.data());
        std::printf("first run: %ld allocations, %.1f MB\nlater runs (allocations, MB):", g_allocs.load() - before,
                    (g_bytes.load() - bytes) / 1e6);
        for (int r = 0; r < runs; ++r) {
            before = g_allocs.load(), bytes = g_bytes.load();
            runner.run(pixels.data(), H, W, K.data(), T.data(), occupancy.data(), density.data());
            std::printf(" %ld %.2f;", g_allocs.load() - before, (g_bytes.load() - bytes) / 1e6);
        }
        std::printf("\n");
    } catch (const std::exception& e) {
        std::fprintf(stderr, "occflownet-alloc-probe: %s\n", e.what());
        return 1;
    }
    return 0;
}
