// occflownet embedding runtime (C++17): run a contract-v1 occupancy model -- one plain ONNX file, preprocessing
// inside the graph, standard operators only -- through the onnxruntime C/C++ API.
//
// Contract v1 (what a model file must be, checked by Runner's constructor):
//   inputs   images     uint8   [B, 6, H, W, 3]  RGB, cameras in the model's `cameras` order, any H x W
//            intrinsics float32 [B, 6, 3, 3]     pinhole matrix for that H x W (OpenCV camera: x right, y down,
//                                                z forward; integer pixel coordinates are pixel centres)
//            cam2ego    float32 [B, 6, 4, 4]     OpenCV camera frame -> ego frame (x forward, y left, z up), metres
//   outputs  occupancy  uint8   [B, X, Y, Z]     Occ3D grid [x, y, z] of the ego frame, classes 0..16, free_index
//                                                (17) = free; X, Y, Z = grid.shape (200, 200, 16)
//            density    float32 [B, X, Y, Z]     occupancy probability sigma
//   metadata_props (JSON values): classes, free_index, grid {lower, upper, voxel_size, shape}, cameras,
//            class_colors, threshold, input_size [H, W], default_calibration (calibration JSON with image_size),
//            onnx_contract == "v1"; optional preset, occflownet_version.
// All arrays are C order (row-major), batch 1 in this API. The names, dtypes, ranks, fixed dimensions, metadata keys
// and calibration tolerances are the constants of occflownet/contract_v1.hpp (namespace occflownet::contract),
// generated from the Python definitions in occflownet/contract/ (`python -m occflownet.contract.cpp_header`).
#pragma once

#include "occflownet/contract_v1.hpp"

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace occflownet {

constexpr int kCameras = contract::kNumCameras;
constexpr double kAspectTolerance = contract::kAspectTolerance;  // relative aspect-ratio difference allowed when
                                                                 // rescaling intrinsics
constexpr double kOrthonormalTolerance = contract::kOrthonormalTolerance;  // max |R^T R - I| of a cam2ego rotation

// Every failure of this library is an Error (never an abort); what() names the file, camera or field.
class Error : public std::runtime_error {
public:
    enum Code { kInvalidArgument = 1, kContract = 2, kRuntime = 3, kIO = 4 };
    Error(Code code, const std::string& message) : std::runtime_error(message), code_(code) {}
    Code code() const noexcept { return code_; }

private:
    Code code_;
};

// The voxel grid of the ego frame; voxel (i, j, k) has its centre at lower + (index + 0.5) * voxel_size.
struct GridSpec {
    std::array<double, 3> lower{}, upper{};
    double voxel_size = 0.0;
    std::array<int, 3> shape{};   // [X, Y, Z]
    std::size_t voxels() const { return std::size_t(shape[0]) * shape[1] * shape[2]; }
};

// A validated calibration of the six cameras, in the order it was parsed for (the model's camera order).
struct Calibration {
    std::vector<std::string> cameras;                 // 6 names
    std::vector<std::array<double, 9>> intrinsics;    // per camera, row-major 3x3, pixels
    std::vector<std::array<double, 16>> cam2ego;      // per camera, row-major 4x4, camera -> ego, metres
    std::vector<std::array<int, 2>> image_size;       // per camera [w, h] the intrinsics are for; {0, 0} = not
                                                      // stated (taken to be for the images as given)

    // cam2ego as float32 [6, 4, 4] into out (96 floats).
    void cam2ego_f32(float* out) const;
    // Intrinsics float32 [6, 3, 3] into out (54 floats) for images of width x height. When a camera's stated size
    // differs and the aspect ratio agrees within kAspectTolerance: s = w/W (x), h/H (y), f' = f s and
    // c' = (c + 0.5) s - 0.5 (pixel centres); skew scales with x. A different aspect ratio -> Error(kInvalidArgument)
    // naming the camera (the images were cropped or padded in a way the calibration does not describe).
    // reduction n > 1: the width x height images were decoded at 1/n (a JPEG at reduced scale, the contract's rule):
    // the intrinsics are then scaled by s = 1/n exactly, f' = f / n, c' = (c + 0.5) / n - 0.5, in double before
    // the one cast to float (as occflownet.contract's Calibration.arrays_for); an entry beyond float32 after the
    // rescaling -> Error(kInvalidArgument) naming the camera.
    void intrinsics_for_size(int width, int height, float* out, int reduction = 1) const;
};

// Calibration JSON -> Calibration for `cameras` (in that order). The JSON is
//   {"cameras": {"CAM_FRONT": {"intrinsic": 3x3, "cam2ego": 4x4, "image_size": [w, h] (optional)}, ...},
//    "image_size": [w, h] (optional, for cameras without their own)}; other keys are ignored.
// Checked before parsing: at most contract::kMaxCalibrationBytes bytes, nested at most kMaxCalibrationDepth arrays
// and objects deep. Then: every camera present, shapes, every entry a JSON number (not a boolean, not a string)
// whose float32 is finite (|x| < kFloat32Limit), intrinsic non-singular with last row [0, 0, 1] and positive focal
// lengths, cam2ego last row [0, 0, 0, 1] and a proper rotation (orthonormal within kOrthonormalTolerance, det > 0),
// image sizes integers 1..kMaxImageSide. The rules and messages of occflownet.contract (docs/contracts.md):
// Error(kInvalidArgument) names `source`, the camera and the field down to the entry ("CAM_FRONT intrinsic[0][0]
// must be a JSON number, got true").
Calibration parse_calibration(const std::string& json_text, const std::vector<std::string>& cameras,
                              const std::string& source = "calibration");

// The model's contract-v1 metadata.
struct ModelInfo {
    std::string path;
    std::string contract;                       // "v1"
    std::vector<std::string> classes;           // names, index = class id
    int free_index = -1;                        // classes[free_index] is free space
    GridSpec grid;
    std::vector<std::string> cameras;           // the six camera names, input order
    std::vector<std::array<std::uint8_t, 3>> class_colors;   // RGB per class
    double threshold = 0.0;                     // tau of the sigma >= tau fusion (informational)
    std::array<int, 2> input_size{};            // [H, W] the graph resizes to internally (informational)
    std::string preset, version;                // may be empty
    Calibration default_calibration;            // the training rig, with its image size
    std::array<int, 2> fixed_image_size{};      // [H, W] if the graph pins the image size, else {0, 0}
};

struct RunnerOptions {
    int intra_op_threads = 0;     // 0: onnxruntime's default (one per physical core)
    bool allow_spinning = false;  // idle ORT threads busy-wait (a little faster on an idle machine)
    // "cpu" (default), "cuda" (device_id), or any name onnxruntime's generic AppendExecutionProvider accepts
    // ("XNNPACK", "OpenVINO", "QNN", ...); a provider this onnxruntime build lacks -> Error(kRuntime).
    std::string execution_provider = "cpu";
    int device_id = 0;
    std::vector<std::pair<std::string, std::string>> provider_options;
};

// One onnxruntime session of a contract-v1 model. Not thread-safe: one Runner per thread (sessions are cheap to
// share in onnxruntime, but run() keeps per-frame state), or serialise calls.
class Runner {
public:
    // Loads `model_path`, checks inputs/outputs (names, dtypes, ranks, static dims) and metadata.
    // Error(kIO) if unreadable, Error(kContract) naming the file and what breaks contract v1, Error(kRuntime) for
    // onnxruntime failures (e.g. an unavailable execution provider).
    explicit Runner(const std::string& model_path, const RunnerOptions& options = {});
    ~Runner();
    Runner(Runner&&) noexcept;
    Runner& operator=(Runner&&) noexcept;
    Runner(const Runner&) = delete;
    Runner& operator=(const Runner&) = delete;

    const ModelInfo& info() const;

    // One frame, caller-owned buffers (C order):
    //   images     uint8   [6, height, width, 3] RGB, info().cameras order
    //   intrinsics float32 [6, 3, 3] for height x width (see Calibration::intrinsics_for_size)
    //   cam2ego    float32 [6, 4, 4]
    //   occupancy  uint8   [X, Y, Z] (info().grid.voxels() bytes), written
    //   density    float32 [X, Y, Z] written, or nullptr (not fetched)
    // The tensors wrap these buffers (no copies). With the same buffers and size as the previous call, nothing is
    // allocated by this library; other buffers cost a few small tensor headers. onnxruntime itself still allocates
    // inside each run (tiny: ~2,000 allocations, ~18 MB; docs/embed.md), as it does for Python.
    void run(const std::uint8_t* images, int height, int width, const float* intrinsics, const float* cam2ego,
             std::uint8_t* occupancy, float* density);

    // The onnxruntime library version in use (e.g. "1.32.0").
    static std::string onnxruntime_version();

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace occflownet
