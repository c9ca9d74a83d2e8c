// occflownet-run: one frame of six camera images -> Occ3D occupancy grid (.npy), through the occflownet runner.
//
//   occflownet-run --model m.onnx --images DIR [--calib calib.json] --out grid.npy [--runs N] [--threads T]
//                  [--provider cpu|cuda|...] [--spin] [--density-out density.npy] [--intrinsics-out K.npy]
//                  [--images-out images.npy]
//
// DIR holds <CAMERA>.jpg (or .jpeg/.png) per camera of the model. Without --calib the model's default calibration
// is used. Calibration intrinsics for another image size with the same aspect ratio are rescaled (pixel-centre rule,
// see Calibration::intrinsics_for_size). JPEGs are decoded at reduced scale (libjpeg's DCT scaling, 1/n with n the
// contract's rule for the model's input size; the intrinsics follow with s = 1/n). After one warm-up run, N timed runs each decode the six images (from
// memory) into the input buffer and run the model; p50 latencies with and without decoding are printed, then the
// per-class voxel counts of the grid. Exit status 0 on success, 1 on any error (message on stderr), 2 on bad usage.
#include "frame_io.hpp"
#include "occflownet/runner.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <string>
#include <vector>

namespace {

using occflownet::Error;
using Clock = std::chrono::steady_clock;

struct Args {
    std::string model, images, calib, out, density_out, intrinsics_out, images_out, provider = "cpu";
    int runs = 1, threads = 0;
    bool spin = false;
};

const char* kUsage =
    "usage: occflownet-run --model m.onnx --images DIR [--calib calib.json] --out grid.npy [--runs N]\n"
    "                      [--threads T] [--provider cpu|cuda|NAME] [--spin] [--density-out density.npy]\n"
    "                      [--intrinsics-out K.npy] [--images-out images.npy]\n";

[[noreturn]] void usage(const std::string& message) {
    std::cerr << "occflownet-run: " << message << "\n" << kUsage;
    std::exit(2);
}

int to_int(const std::string& flag, const std::string& v, int lo) {
    char* end = nullptr;
    long x = std::strtol(v.c_str(), &end, 10);
    if (v.empty() || *end || x < lo || x > 1000000) usage(flag + " needs an integer >= " + std::to_string(lo));
    return int(x);
}

Args parse(int argc, char** argv) {
    Args a;
    for (int i = 1; i < argc; ++i) {
        std::string flag = argv[i];
        if (flag == "-h" || flag == "--help") {
            std::cout << kUsage;
            std::exit(0);
        }
        if (flag == "--spin") {
            a.spin = true;
            continue;
        }
        if (i + 1 >= argc) usage(flag + " needs a value");
        std::string v = argv[++i];
        if (flag == "--model") a.model = v;
        else if (flag == "--images") a.images = v;
        else if (flag == "--calib") a.calib = v;
        else if (flag == "--out") a.out = v;
        else if (flag == "--density-out") a.density_out = v;
        else if (flag == "--intrinsics-out") a.intrinsics_out = v;
        else if (flag == "--images-out") a.images_out = v;
        else if (flag == "--provider") a.provider = v;
        else if (flag == "--runs") a.runs = to_int(flag, v, 1);
        else if (flag == "--threads") a.threads = to_int(flag, v, 0);
        else usage("unknown option " + flag);
    }
    if (a.model.empty() || a.images.empty() || a.out.empty()) usage("--model, --images and --out are required");
    return a;
}

double ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

double median(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    std::size_t n = v.size();
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

int run(const Args& a) {
    auto t_load = Clock::now();
    occflownet::RunnerOptions options;
    options.intra_op_threads = a.threads;
    options.allow_spinning = a.spin;
    options.execution_provider = a.provider;
    occflownet::Runner runner(a.model, options);
    const occflownet::ModelInfo& info = runner.info();
    const double load_ms = ms(Clock::now() - t_load);

    // Six encoded images (read once), all the same size.
    std::vector<occflownet::io::EncodedImage> images;
    for (const std::string& path : occflownet::io::find_camera_images(a.images, info.cameras))
        images.push_back(occflownet::io::probe_image(path));
    const int W0 = images[0].width, H0 = images[0].height;
    for (const auto& im : images)
        if (im.width != W0 || im.height != H0) {
            std::string detail;
            for (std::size_t c = 0; c < images.size(); ++c)
                detail += (c ? ", " : "") + info.cameras[c] + ": " + std::to_string(images[c].width) + "x" +
                          std::to_string(images[c].height);
            throw Error(Error::kInvalidArgument, a.images + ": camera images differ in size (" + detail +
                                                     "); all six must match");
        }

    // JPEGs are decoded at 1/n (the contract's reduced-scale rule, frame_io.hpp decode_reduction): the smallest
    // scale that still holds the network input. n is the same for the six (same size, same format checked below).
    const int n = occflownet::io::decode_reduction(images[0], info.input_size);
    for (const auto& im : images)
        if (occflownet::io::decode_reduction(im, info.input_size) != n)
            throw Error(Error::kInvalidArgument, a.images + ": camera images mix JPEG and PNG; all six must match");
    const int W = (W0 + n - 1) / n, H = (H0 + n - 1) / n;

    // Calibration for W0 x H0 as stored, scaled to the decoded W x H.
    occflownet::Calibration calib =
        a.calib.empty() ? info.default_calibration
                        : occflownet::parse_calibration(
                              occflownet::io::read_text(a.calib, occflownet::contract::kMaxCalibrationBytes),
                              info.cameras, a.calib);
    std::vector<float> K(occflownet::kCameras * 9), T(occflownet::kCameras * 16);
    calib.intrinsics_for_size(W0, H0, K.data(), n);
    calib.cam2ego_f32(T.data());

    // Caller-owned buffers, allocated once.
    const std::size_t frame = std::size_t(W) * H * 3;
    std::vector<std::uint8_t> pixels(frame * occflownet::kCameras), occupancy(info.grid.voxels());
    std::vector<float> density(info.grid.voxels());
    auto decode_all = [&] { occflownet::io::decode_all_into(images, pixels.data(), frame, n); };

    std::vector<double> total, infer;
    double first_ms = 0;
    for (int r = 0; r <= a.runs; ++r) {  // run 0: warm-up
        auto t0 = Clock::now();
        decode_all();
        auto t1 = Clock::now();
        runner.run(pixels.data(), H, W, K.data(), T.data(), occupancy.data(), density.data());
        auto t2 = Clock::now();
        if (r == 0) first_ms = ms(t2 - t1);
        else total.push_back(ms(t2 - t0)), infer.push_back(ms(t2 - t1));
    }

    const auto& g = info.grid.shape;
    const std::vector<std::size_t> shape{std::size_t(g[0]), std::size_t(g[1]), std::size_t(g[2])};
    occflownet::io::write_npy(a.out, "|u1", shape, occupancy.data(), occupancy.size());
    if (!a.density_out.empty())
        occflownet::io::write_npy(a.density_out, "<f4", shape, density.data(), density.size() * sizeof(float));
    if (!a.intrinsics_out.empty())
        occflownet::io::write_npy(a.intrinsics_out, "<f4", {occflownet::kCameras, 3, 3}, K.data(), K.size() * 4);
    if (!a.images_out.empty())  // the decoded input, uint8 [6, H, W, 3] RGB
        occflownet::io::write_npy(a.images_out, "|u1", {occflownet::kCameras, std::size_t(H), std::size_t(W), 3},
                                  pixels.data(), pixels.size());

    std::printf("model: %s (preset %s, occflownet %s, contract %s), onnxruntime %s, provider %s, threads %d\n",
                a.model.c_str(), info.preset.empty() ? "?" : info.preset.c_str(),
                info.version.empty() ? "?" : info.version.c_str(), info.contract.c_str(),
                occflownet::Runner::onnxruntime_version().c_str(), a.provider.c_str(), a.threads);
    std::printf("images: %s, 6 x %dx%d decoded at 1/%d from %dx%d; calibration: %s\n", a.images.c_str(), W, H, n, W0, H0,
                a.calib.empty() ? "model default" : a.calib.c_str());
    std::printf("load: %.1f ms, first run: %.1f ms\n", load_ms, first_ms);
    std::printf("p50 inference: %.2f ms, p50 decode+inference: %.2f ms (%d runs)\n", median(infer), median(total),
                a.runs);
    std::printf("wrote %s: uint8 [%d, %d, %d]\n", a.out.c_str(), g[0], g[1], g[2]);
    std::vector<std::size_t> counts(info.classes.size(), 0);
    for (std::uint8_t v : occupancy)
        if (v < counts.size()) ++counts[v];
    std::printf("class counts:\n");
    for (std::size_t c = 0; c < counts.size(); ++c) std::printf("  %2zu %-22s %zu\n", c, info.classes[c].c_str(), counts[c]);
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    Args args = parse(argc, argv);
    try {
        return run(args);
    } catch (const std::exception& e) {
        std::cerr << "occflownet-run: error: " << e.what() << "\n";
        return 1;
    }
}
