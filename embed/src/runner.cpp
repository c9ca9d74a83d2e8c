// occflownet embedding runtime: contract-v1 model loading and checks, calibration parsing, one-frame inference,
// and the extern "C" layer. See occflownet/runner.hpp for the shapes and frames at every boundary.
#define ORT_API_MANUAL_INIT  // initialise the API ourselves: an onnxruntime older than the headers is an Error
#include "occflownet/runner.h"
#include "occflownet/runner.hpp"

#include <onnxruntime_cxx_api.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <set>
#include <sstream>

namespace occflownet {
namespace {

using nlohmann::json;

[[noreturn]] void fail(Error::Code code, const std::string& message) { throw Error(code, message); }

// ------------------------------------------------------------------------------------------- JSON helpers
// The deepest nesting of arrays and objects in JSON text (brackets inside strings do not count), found without
// parsing or recursion (as occflownet.contract.calibration.json_depth); exact for valid JSON.
int json_depth(const std::string& text) {
    int depth = 0, deepest = 0;
    bool in_string = false;
    for (std::size_t i = 0; i < text.size(); ++i) {
        const char ch = text[i];
        if (in_string) {
            if (ch == '\\') ++i;  // the escaped character cannot end the string
            else if (ch == '"') in_string = false;
        } else if (ch == '"') {
            in_string = true;
        } else if (ch == '[' || ch == '{') {
            deepest = std::max(deepest, ++depth);
        } else if (ch == ']' || ch == '}') {
            --depth;
        }
    }
    return deepest;
}

// Calibration JSON text -> its JSON value, refusing before it is parsed text of more than kMaxCalibrationBytes or
// nested deeper than kMaxCalibrationDepth (nlohmann's parser sets no depth limit); Error naming `source`.
json parse_calibration_text(const std::string& text, const std::string& source) {
    if (text.size() > contract::kMaxCalibrationBytes)
        fail(Error::kInvalidArgument, source + " is " + std::to_string(text.size()) + " bytes, over the limit of " +
                                          std::to_string(contract::kMaxCalibrationBytes) + " bytes");
    if (json_depth(text) > contract::kMaxCalibrationDepth)
        fail(Error::kInvalidArgument, source + " is nested deeper than " +
                                          std::to_string(contract::kMaxCalibrationDepth) +
                                          " levels of arrays and objects");
    json calib = json::parse(text, nullptr, false);
    if (calib.is_discarded()) fail(Error::kInvalidArgument, source + ": not valid JSON");
    return calib;
}

// `value` as it reads in JSON (true, "1266.4", 1e+308, [1000000000.0, 54]) for messages, shortened.
std::string token(const json& value) {
    std::string text;
    if (value.is_number_float() && !std::isfinite(value.get<double>())) {
        text = std::isnan(value.get<double>()) ? "nan" : value.get<double>() > 0 ? "inf" : "-inf";
    } else if (value.is_array() && value.size() <= 4) {
        for (const json& item : value) text += (text.empty() ? "[" : ", ") + token(item);
        text = text.empty() ? "[]" : text + "]";
    } else {
        text = value.dump();
    }
    return text.size() <= 40 ? text : text.substr(0, 37) + "...";
}

// One JSON number -> double; Error naming `where` for a boolean, a string or anything not a number, and for a
// number whose float32 is not finite (the model gets float32).
double number(const json& value, const std::string& where) {
    if (!value.is_number()) fail(Error::kInvalidArgument, where + " must be a JSON number, got " + token(value));
    const double x = value.get<double>();
    if (!(std::fabs(x) < contract::kFloat32Limit))
        fail(Error::kInvalidArgument, where + " must be finite in float32, got " + token(value));
    return x;
}

// Number matrix rows x cols (row-major) from a JSON array of arrays; Error naming `where` (and the entry).
template <std::size_t N>
std::array<double, N> matrix(const json& value, int rows, int cols, const std::string& where) {
    const std::string shape = std::to_string(rows) + "x" + std::to_string(cols);
    bool arrays = value.is_array() && int(value.size()) == rows;
    for (int r = 0; arrays && r < rows; ++r) arrays = value[r].is_array();
    if (!arrays) fail(Error::kInvalidArgument, where + " must be a " + shape + " array of numbers");
    std::string lengths;
    bool ragged = false;
    for (int r = 0; r < rows; ++r) {
        lengths += (r ? ", " : "") + std::to_string(value[r].size());
        ragged = ragged || int(value[r].size()) != cols;
    }
    if (ragged) fail(Error::kInvalidArgument, where + " must be " + shape + ", got rows of [" + lengths + "]");
    std::array<double, N> out{};
    for (int r = 0; r < rows; ++r)
        for (int c = 0; c < cols; ++c)
            out[r * cols + c] =
                number(value[r][c], where + "[" + std::to_string(r) + "][" + std::to_string(c) + "]");
    return out;
}

std::array<int, 2> image_size(const json& value, const std::string& where) {
    if (!value.is_array() || value.size() != 2) fail(Error::kInvalidArgument, where + " must be [width, height]");
    std::array<int, 2> out{};
    const double v[2] = {number(value[0], where + "[0]"), number(value[1], where + "[1]")};
    for (int i = 0; i < 2; ++i) {
        if (!(v[i] >= 1 && v[i] <= contract::kMaxImageSide && v[i] == std::floor(v[i])))
            fail(Error::kInvalidArgument, where + " must be two integers from 1 to " +
                                              std::to_string(contract::kMaxImageSide) + ", got " + token(value));
        out[i] = int(v[i]);
    }
    return out;
}

// np.allclose(a, b, atol) semantics: |a - b| <= atol + 1e-5 |b|
bool close(double a, double b, double atol) { return std::fabs(a - b) <= atol + 1e-5 * std::fabs(b); }

double det3(const double* m, int stride) {  // determinant of a 3x3 block with row stride `stride`
    const double *r0 = m, *r1 = m + stride, *r2 = m + 2 * stride;
    return r0[0] * (r1[1] * r2[2] - r1[2] * r2[1]) - r0[1] * (r1[0] * r2[2] - r1[2] * r2[0]) +
           r0[2] * (r1[0] * r2[1] - r1[1] * r2[0]);
}

std::string fmt(double v, int digits = 3) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.*f", digits, v);
    return buf;
}

Calibration calibration_from_json(const json& calib, const std::vector<std::string>& cameras,
                                  const std::string& source) {
    const std::string pre = source + ": ";
    if (!calib.is_object()) fail(Error::kInvalidArgument, pre + "calibration must be a JSON object");
    auto cams = calib.find("cameras");
    if (cams == calib.end() || !cams->is_object())
        fail(Error::kInvalidArgument, pre + "calibration has no 'cameras' object");
    std::array<int, 2> top{};
    if (calib.contains("image_size")) top = image_size(calib["image_size"], pre + "calibration image_size");
    Calibration out;
    for (const std::string& name : cameras) {
        auto entry = cams->find(name);
        if (entry == cams->end() || !entry->is_object()) {
            std::string have;
            for (auto it = cams->begin(); it != cams->end(); ++it) have += (have.empty() ? "" : ", ") + it.key();
            fail(Error::kInvalidArgument, pre + "calibration lacks camera " + name + " (has " + have + ")");
        }
        for (const char* key : {"intrinsic", "cam2ego"})
            if (!entry->contains(key))
                fail(Error::kInvalidArgument, pre + "calibration of " + name + " lacks '" + key + "'");
        auto K = matrix<9>((*entry)["intrinsic"], 3, 3, pre + name + " intrinsic");
        double d = det3(K.data(), 3);
        if (std::fabs(d) < contract::kSingularTolerance)
            fail(Error::kInvalidArgument, pre + name + " intrinsic is singular");
        if (!(close(K[6], 0, 1e-6) && close(K[7], 0, 1e-6) && close(K[8], 1, 1e-6)))
            fail(Error::kInvalidArgument, pre + name + " intrinsic last row must be [0, 0, 1]");
        if (!(K[0] > 0 && K[4] > 0))
            fail(Error::kInvalidArgument, pre + name + " intrinsic focal lengths must be positive, got fx=" +
                                              fmt(K[0]) + ", fy=" + fmt(K[4]));
        auto T = matrix<16>((*entry)["cam2ego"], 4, 4, pre + name + " cam2ego");
        if (!(close(T[12], 0, 1e-6) && close(T[13], 0, 1e-6) && close(T[14], 0, 1e-6) && close(T[15], 1, 1e-6)))
            fail(Error::kInvalidArgument, pre + name + " cam2ego last row must be [0, 0, 0, 1]");
        double worst = 0;  // max |R^T R - I|
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) {
                double dot = 0;
                for (int k = 0; k < 3; ++k) dot += T[k * 4 + i] * T[k * 4 + j];
                worst = std::max(worst, std::fabs(dot - (i == j ? 1.0 : 0.0)));
            }
        if (worst > kOrthonormalTolerance || det3(T.data(), 4) <= 0)
            fail(Error::kInvalidArgument, pre + name + " cam2ego rotation is not a proper rotation (orthonormal, det +1)");
        std::array<int, 2> size = top;
        if (entry->contains("image_size")) size = image_size((*entry)["image_size"], pre + name + " image_size");
        out.cameras.push_back(name);
        out.intrinsics.push_back(K);
        out.cam2ego.push_back(T);
        out.image_size.push_back(size);
    }
    return out;
}

// ------------------------------------------------------------------------------------------- metadata
namespace key = contract::metadata;

const json& require(const json& meta, const char* key, const std::string& source) {
    auto it = meta.find(key);
    if (it == meta.end()) fail(Error::kContract, source + ": model metadata lacks '" + key + "'");
    return *it;
}

std::vector<std::string> strings(const json& v, const char* key, const std::string& source) {
    if (!v.is_array()) fail(Error::kContract, source + ": metadata '" + key + "' must be a list of strings");
    std::vector<std::string> out;
    for (const json& s : v) {
        if (!s.is_string()) fail(Error::kContract, source + ": metadata '" + key + "' must be a list of strings");
        out.push_back(s.get<std::string>());
    }
    return out;
}

// metadata_props -> JSON values; a value that is not JSON (a foreign key), or is nested deeper than
// kMaxCalibrationDepth arrays and objects (never parsed), stays a plain string.
json decode_metadata(const std::vector<std::pair<std::string, std::string>>& props) {
    json meta = json::object();
    for (const auto& [name, text] : props) {
        json value = json_depth(text) <= contract::kMaxCalibrationDepth ? json::parse(text, nullptr, false)
                                                                         : json(json::value_t::discarded);
        meta[name] = value.is_discarded() ? json(text) : value;
    }
    return meta;
}

// Every required key is there (all missing ones named at once).
void check_required_keys(const json& meta, const std::string& source) {
    std::string missing;
    for (const char* k : key::kRequired)
        if (!meta.contains(k)) missing += (missing.empty() ? "" : ", ") + std::string(k);
    if (!missing.empty())
        fail(Error::kContract, source + ": model metadata lacks " + missing + " (not an occflownet contract-" +
                                   contract::kVersion + " export?)");
}

void check_contract_version(const json& meta, const std::string& source) {
    const json& version = require(meta, key::kOnnxContract, source);
    if (!version.is_string() || version.get<std::string>() != contract::kVersion)
        fail(Error::kContract, source + ": " + key::kOnnxContract + " is " + version.dump() +
                                   ", this library reads \"" + contract::kVersion + "\"");
}

int parse_free_index(const json& meta, std::size_t classes, const std::string& source) {
    const json& free = require(meta, key::kFreeIndex, source);
    if (!free.is_number_integer() || free.get<long>() < 0 || free.get<long>() >= long(classes))
        fail(Error::kContract, source + ": " + key::kFreeIndex + " " + free.dump() + " is not a class index (0.." +
                                   std::to_string(classes) + ")");
    return free.get<int>();
}

std::vector<std::array<std::uint8_t, 3>> parse_class_colors(const json& meta, std::size_t classes,
                                                             const std::string& source) {
    const json& colors = require(meta, key::kClassColors, source);
    const std::string pre = source + ": " + key::kClassColors;
    if (!colors.is_array() || colors.size() != classes)
        fail(Error::kContract, pre + " must have one RGB triple per class");
    std::vector<std::array<std::uint8_t, 3>> out;
    for (const json& c : colors) {
        if (!c.is_array() || c.size() != 3) fail(Error::kContract, pre + " entries must be [r, g, b]");
        std::array<std::uint8_t, 3> rgb{};
        for (int i = 0; i < 3; ++i) {
            if (!c[i].is_number_integer() || c[i].get<long>() < 0 || c[i].get<long>() > 255)
                fail(Error::kContract, pre + " values must be integers 0..255");
            rgb[i] = std::uint8_t(c[i].get<int>());
        }
        out.push_back(rgb);
    }
    return out;
}

GridSpec parse_grid(const json& meta, const std::string& source) {
    const json& grid = require(meta, key::kGrid, source);
    GridSpec out;
    try {
        for (int i = 0; i < 3; ++i) {
            out.lower[i] = grid.at("lower").at(i).get<double>();
            out.upper[i] = grid.at("upper").at(i).get<double>();
            out.shape[i] = grid.at("shape").at(i).get<int>();
            if (out.shape[i] < 1) throw std::runtime_error("shape entries must be positive");
        }
        if (grid.at("shape").size() != 3) throw std::runtime_error("shape must have 3 entries");
        out.voxel_size = grid.at("voxel_size").get<double>();
    } catch (const std::exception& e) {
        fail(Error::kContract, source + ": metadata '" + key::kGrid +
                                   "' must hold lower, upper, voxel_size and shape [X, Y, Z] (" + e.what() + ")");
    }
    return out;
}

std::vector<std::string> parse_cameras(const json& meta, const std::string& source) {
    auto cameras = strings(require(meta, key::kCameras, source), key::kCameras, source);
    if (cameras.size() != std::size_t(contract::kNumCameras) ||
        std::set<std::string>(cameras.begin(), cameras.end()).size() != cameras.size())
        fail(Error::kContract, source + ": metadata '" + key::kCameras + "' must be " +
                                   std::to_string(contract::kNumCameras) + " distinct names");
    return cameras;
}

double parse_threshold(const json& meta, const std::string& source) {
    const json& tau = require(meta, key::kThreshold, source);
    if (!tau.is_number()) fail(Error::kContract, source + ": metadata '" + key::kThreshold + "' must be a number");
    return tau.get<double>();
}

std::array<int, 2> parse_input_size(const json& meta, const std::string& source) {
    const json& size = require(meta, key::kInputSize, source);
    if (!size.is_array() || size.size() != 2 || !size[0].is_number_integer() || !size[1].is_number_integer())
        fail(Error::kContract, source + ": metadata '" + key::kInputSize + "' must be [H, W]");
    return {size[0].get<int>(), size[1].get<int>()};
}

// The default calibration, validated like any calibration for the model's cameras (its errors are kContract).
Calibration parse_default_calibration(const json& meta, const std::vector<std::string>& cameras,
                                      const std::string& source) {
    json calib = require(meta, key::kDefaultCalibration, source);
    const std::string where = source + ": " + key::kDefaultCalibration;
    try {
        if (calib.is_string()) calib = parse_calibration_text(calib.get<std::string>(), where);  // not decoded
        if (!calib.is_object() || !calib.contains("image_size"))
            fail(Error::kContract, where + " must be calibration JSON with image_size [w, h]");
        return calibration_from_json(calib, cameras, where);
    } catch (const Error& e) {
        fail(Error::kContract, e.what());
    }
}

std::string optional_string(const json& meta, const char* k) {
    auto it = meta.find(k);
    return it != meta.end() && it->is_string() ? it->get<std::string>() : std::string();
}

// metadata_props -> ModelInfo, every key checked in turn; Error(kContract) naming `source` and the key.
ModelInfo parse_metadata(const std::vector<std::pair<std::string, std::string>>& props, const std::string& source) {
    const json meta = decode_metadata(props);
    check_required_keys(meta, source);
    check_contract_version(meta, source);
    ModelInfo info;
    info.path = source;
    info.contract = contract::kVersion;
    info.classes = strings(require(meta, key::kClasses, source), key::kClasses, source);
    info.free_index = parse_free_index(meta, info.classes.size(), source);
    info.class_colors = parse_class_colors(meta, info.classes.size(), source);
    info.grid = parse_grid(meta, source);
    info.cameras = parse_cameras(meta, source);
    info.threshold = parse_threshold(meta, source);
    info.input_size = parse_input_size(meta, source);
    info.default_calibration = parse_default_calibration(meta, info.cameras, source);
    info.preset = optional_string(meta, key::kPreset);
    info.version = optional_string(meta, key::kOccflownetVersion);
    return info;
}

// ------------------------------------------------------------------------------------------- session I/O
static_assert(contract::kImages.element_type == ONNX_TENSOR_ELEMENT_DATA_TYPE_UINT8 &&
                  contract::kIntrinsics.element_type == ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT &&
                  contract::kCam2ego.element_type == ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT &&
                  contract::kOccupancy.element_type == ONNX_TENSOR_ELEMENT_DATA_TYPE_UINT8 &&
                  contract::kDensity.element_type == ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT,
              "run() takes uint8 images and occupancy, float intrinsics, cam2ego and density");
constexpr int dynamic_dims(const contract::TensorSpec& spec) {  // after the batch
    int n = 0;
    for (std::size_t d = 1; d < spec.rank; ++d) n += spec.dims[d] < 0;
    return n;
}
static_assert(dynamic_dims(contract::kImages) == 2 && contract::kImages.dims[2] < 0 && contract::kImages.dims[3] < 0 &&
                  dynamic_dims(contract::kIntrinsics) == 0 && dynamic_dims(contract::kCam2ego) == 0,
              "images are [B, V, H, W, 3] with H, W the only dynamic dims after the batch; the matrices are static");
static_assert(contract::kOccupancy.rank == 4 && contract::kDensity.rank == 4, "the outputs are [B, X, Y, Z]");

std::string type_name(ONNXTensorElementDataType t) {
    switch (t) {
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_UINT8: return "uint8";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT: return "float32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT16: return "float16";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64: return "int64";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32: return "int32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_DOUBLE: return "float64";
        default: return "type " + std::to_string(int(t));
    }
}

std::string dims_text(const std::vector<std::int64_t>& dims) {
    std::string s = "[";
    for (std::size_t i = 0; i < dims.size(); ++i) s += (i ? ", " : "") + (dims[i] < 0 ? "?" : std::to_string(dims[i]));
    return s + "]";
}

template <std::size_t N>
std::string joined(const std::array<const char*, N>& names) {
    std::string s;
    for (const char* n : names) s += (s.empty() ? "" : ", ") + std::string(n);
    return s;
}

// What one graph input or output must be: name, element type, dims (-1 = any).
struct Want {
    std::string name;
    ONNXTensorElementDataType type;
    std::vector<std::int64_t> dims;
};

Want want(const contract::TensorSpec& spec) {
    return {spec.name, ONNXTensorElementDataType(spec.element_type),
            std::vector<std::int64_t>(spec.dims.begin(), spec.dims.begin() + spec.rank)};
}

std::vector<Want> input_wants() {
    std::vector<Want> out;
    for (const auto& spec : contract::kInputs) out.push_back(want(spec));
    return out;
}

// The outputs [B, X, Y, Z] with the grid shape the model's metadata states (run() writes grid.voxels() values).
std::vector<Want> output_wants(const GridSpec& grid) {
    std::vector<Want> out;
    for (const auto& spec : contract::kOutputs) {
        out.push_back(want(spec));
        std::copy(grid.shape.begin(), grid.shape.end(), out.back().dims.begin() + 1);
    }
    return out;
}

std::vector<std::string> graph_names(Ort::Session& session, bool inputs) {
    Ort::AllocatorWithDefaultOptions alloc;
    std::size_t n = inputs ? session.GetInputCount() : session.GetOutputCount();
    std::vector<std::string> names;
    for (std::size_t i = 0; i < n; ++i)
        names.push_back(inputs ? session.GetInputNameAllocated(i, alloc).get()
                               : session.GetOutputNameAllocated(i, alloc).get());
    return names;
}

// Checks one side (inputs or outputs) against `wants`, in the contract's order. Returns the dims found.
std::vector<std::vector<std::int64_t>> check_signature(Ort::Session& session, bool inputs,
                                                       const std::vector<Want>& wants, const std::string& source) {
    const std::vector<std::string> found = graph_names(session, inputs);
    const std::string kind = inputs ? "input" : "output";
    const std::string needs = std::string("contract ") + contract::kVersion + " needs ";
    std::vector<std::vector<std::int64_t>> dims_out;
    for (const Want& w : wants) {
        auto it = std::find(found.begin(), found.end(), w.name);
        if (it == found.end()) {
            std::string have;
            for (auto& f : found) have += (have.empty() ? "" : ", ") + f;
            fail(Error::kContract, source + ": model has no " + kind + " '" + w.name + "' (has " + have + "); " +
                                       needs + "inputs " + joined(contract::kInputNames) + " and outputs " +
                                       joined(contract::kOutputNames));
        }
        std::size_t idx = std::size_t(it - found.begin());
        Ort::TypeInfo type = inputs ? session.GetInputTypeInfo(idx) : session.GetOutputTypeInfo(idx);
        if (type.GetONNXType() != ONNX_TYPE_TENSOR)
            fail(Error::kContract, source + ": " + kind + " '" + w.name + "' is not a tensor");
        auto tensor = type.GetTensorTypeAndShapeInfo();
        auto dims = tensor.GetShape();
        bool ok = tensor.GetElementType() == w.type && dims.size() == w.dims.size();
        for (std::size_t d = 0; ok && d < dims.size(); ++d)
            if (w.dims[d] >= 0 && dims[d] >= 0 && dims[d] != w.dims[d]) ok = false;
        if (!ok)
            fail(Error::kContract, source + ": " + kind + " '" + w.name + "' is " +
                                       type_name(tensor.GetElementType()) + " " + dims_text(dims) + ", " + needs +
                                       type_name(w.type) + " " + dims_text(w.dims));
        dims_out.push_back(dims);
    }
    return dims_out;
}

// One frame's shape of a tensor: the batch 1, then `dims` (its own rank); count = the number of elements.
struct FrameShape {
    std::array<std::int64_t, contract::kMaxRank> dims{};
    std::size_t rank = 0, count = 1;
};

// `spec` for one frame: batch 1, its static dims, and its dynamic ones (the images' H, W) from `fill` in order.
FrameShape frame_shape(const contract::TensorSpec& spec, std::array<std::int64_t, 2> fill = {}) {
    FrameShape s;
    s.rank = spec.rank;
    std::size_t next = 0;
    for (std::size_t d = 0; d < spec.rank; ++d) {
        s.dims[d] = d == 0 ? 1 : spec.dims[d] >= 0 ? spec.dims[d] : fill[next++];
        s.count *= std::size_t(s.dims[d]);
    }
    return s;
}

// An output for one frame: [1, X, Y, Z] of the model's grid.
FrameShape grid_shape(const GridSpec& grid) {
    FrameShape s;
    s.rank = 4;
    s.dims = {1, grid.shape[0], grid.shape[1], grid.shape[2]};
    s.count = grid.voxels();
    return s;
}

std::string provider_list() {
    std::string s;
    for (auto& p : Ort::GetAvailableProviders()) s += (s.empty() ? "" : ", ") + p;
    return s;
}

const OrtApi* init_api() {
    static const OrtApi* api = [] {
        const OrtApi* a = OrtGetApiBase()->GetApi(ORT_API_VERSION);
        if (a) Ort::InitApi(a);
        return a;
    }();
    if (!api)
        fail(Error::kRuntime, std::string("onnxruntime library ") + OrtGetApiBase()->GetVersionString() +
                                  " is older than the headers this program was built with (API version " +
                                  std::to_string(ORT_API_VERSION) + ")");
    return api;
}

// ------------------------------------------------------------------------------------------- opening a model
void check_readable(const std::string& model_path) {
    std::ifstream probe(model_path, std::ios::binary);
    if (!probe) fail(Error::kIO, "model file not found or unreadable: " + model_path);
}

void append_cuda(Ort::SessionOptions& so, const RunnerOptions& options) {
    const OrtApi& api = Ort::GetApi();
    OrtCUDAProviderOptionsV2* cuda = nullptr;
    Ort::ThrowOnError(api.CreateCUDAProviderOptions(&cuda));
    std::unique_ptr<OrtCUDAProviderOptionsV2, void (*)(OrtCUDAProviderOptionsV2*)> guard(
        cuda, api.ReleaseCUDAProviderOptions);
    std::vector<std::string> keys{"device_id"}, values{std::to_string(options.device_id)};
    for (auto& [k, v] : options.provider_options) keys.push_back(k), values.push_back(v);
    std::vector<const char*> kp, vp;
    for (std::size_t i = 0; i < keys.size(); ++i) kp.push_back(keys[i].c_str()), vp.push_back(values[i].c_str());
    Ort::ThrowOnError(api.UpdateCUDAProviderOptions(cuda, kp.data(), vp.data(), kp.size()));
    so.AppendExecutionProvider_CUDA_V2(*cuda);
}

// "cpu" (or empty): nothing to add; "cuda": CUDA with device_id; else onnxruntime's generic provider by name.
void append_execution_provider(Ort::SessionOptions& so, const RunnerOptions& options) {
    std::string ep = options.execution_provider;
    std::transform(ep.begin(), ep.end(), ep.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
    try {
        if (ep == "cuda") {
            append_cuda(so, options);
        } else if (!ep.empty() && ep != "cpu") {
            std::unordered_map<std::string, std::string> opts(options.provider_options.begin(),
                                                              options.provider_options.end());
            so.AppendExecutionProvider(options.execution_provider, opts);
        }
    } catch (const Ort::Exception& e) {
        fail(Error::kRuntime, "execution provider '" + options.execution_provider +
                                  "' is not usable with this onnxruntime (" + e.what() +
                                  "; available: " + provider_list() + ")");
    }
}

Ort::SessionOptions session_options(const RunnerOptions& options) {
    Ort::SessionOptions so;
    so.SetIntraOpNumThreads(std::max(0, options.intra_op_threads));
    so.SetInterOpNumThreads(1);
    so.SetExecutionMode(ExecutionMode::ORT_SEQUENTIAL);
    so.SetGraphOptimizationLevel(GraphOptimizationLevel::ORT_ENABLE_ALL);
    so.AddConfigEntry("session.intra_op.allow_spinning", options.allow_spinning ? "1" : "0");
    append_execution_provider(so, options);
    return so;
}

Ort::Session open_session(const Ort::Env& env, const std::string& model_path, const Ort::SessionOptions& so) {
    try {
        return Ort::Session(env, model_path.c_str(), so);
    } catch (const Ort::Exception& e) {
        fail(Error::kContract, model_path + ": onnxruntime cannot load this model (" + e.what() + ")");
    }
}

std::vector<std::pair<std::string, std::string>> metadata_props(Ort::Session& session) {
    Ort::AllocatorWithDefaultOptions alloc;
    Ort::ModelMetadata meta = session.GetModelMetadata();
    std::vector<std::pair<std::string, std::string>> props;
    for (auto& key : meta.GetCustomMetadataMapKeysAllocated(alloc))
        props.emplace_back(key.get(), meta.LookupCustomMetadataMapAllocated(key.get(), alloc).get());
    return props;
}

// The session against contract v1 -> its ModelInfo: inputs, then metadata, then the outputs (whose grid is the
// metadata's); fixed_image_size from the images input when the graph pins H and W.
ModelInfo check_model(Ort::Session& session, const std::string& source) {
    const auto in_dims = check_signature(session, true, input_wants(), source);
    ModelInfo info = parse_metadata(metadata_props(session), source);
    check_signature(session, false, output_wants(info.grid), source);
    const auto& img = in_dims[0];
    if (img[2] > 0 && img[3] > 0) info.fixed_image_size = {int(img[2]), int(img[3])};
    return info;
}

}  // namespace

// ------------------------------------------------------------------------------------------- Calibration
Calibration parse_calibration(const std::string& json_text, const std::vector<std::string>& cameras,
                              const std::string& source) {
    return calibration_from_json(parse_calibration_text(json_text, source), cameras, source);
}

void Calibration::cam2ego_f32(float* out) const {
    for (std::size_t c = 0; c < cam2ego.size(); ++c)
        for (int i = 0; i < 16; ++i) out[c * 16 + i] = float(cam2ego[c][i]);
}

void Calibration::intrinsics_for_size(int width, int height, float* out, int reduction) const {
    if (width < 1 || height < 1) fail(Error::kInvalidArgument, "image size must be positive");
    if (reduction < 1) fail(Error::kInvalidArgument, "reduction must be positive");
    for (std::size_t c = 0; c < intrinsics.size(); ++c) {
        std::array<double, 9> K = intrinsics[c];
        auto [cw, ch] = image_size[c];
        if (cw > 0 && (cw != width || ch != height)) {
            double aspect = double(width) / height, calib_aspect = double(cw) / ch;
            if (std::fabs(aspect / calib_aspect - 1.0) > kAspectTolerance)
                fail(Error::kInvalidArgument,
                     cameras[c] + ": image is " + std::to_string(width) + "x" + std::to_string(height) +
                         " but the calibration is for " + std::to_string(cw) + "x" + std::to_string(ch) +
                         " (aspect ratio " + fmt(aspect) + " vs " + fmt(calib_aspect) +
                         "); give a calibration with intrinsics for " + std::to_string(width) + "x" +
                         std::to_string(height) + " images");
            double sx = double(width) / cw, sy = double(height) / ch;
            for (int j = 0; j < 3; ++j) K[j] *= sx, K[3 + j] *= sy;
            K[2] += 0.5 * sx - 0.5;  // pixel centres: c' = (c + 0.5) s - 0.5
            K[5] += 0.5 * sy - 0.5;
        }
        if (reduction > 1) {  // decoded at 1/n: the same rule with s = 1/n exactly
            const double s = 1.0 / reduction;
            for (int j = 0; j < 6; ++j) K[j] *= s;
            K[2] += 0.5 * s - 0.5;
            K[5] += 0.5 * s - 0.5;
        }
        for (int i = 0; i < 9; ++i)
            if (!(std::fabs(K[i]) < contract::kFloat32Limit))
                fail(Error::kInvalidArgument, cameras[c] + " intrinsic rescaled for a " + std::to_string(width) + "x" +
                                                  std::to_string(height) + " image is not finite in float32");
        for (int i = 0; i < 9; ++i) out[c * 9 + i] = float(K[i]);
    }
}

// ------------------------------------------------------------------------------------------- Runner
struct Runner::Impl {
    Ort::Env env{nullptr};
    Ort::Session session{nullptr};
    Ort::MemoryInfo memory{nullptr};
    ModelInfo info;
    // Tensors over the caller's buffers of the previous call (reused when the same buffers come again).
    struct Bound {
        const void* ptr[5] = {};
        int height = 0, width = 0;
        std::vector<Ort::Value> inputs, outputs;
    } bound;
};

Runner::Runner(const std::string& model_path, const RunnerOptions& options) {
    init_api();  // first: even empty Ort:: handles call the API when destroyed
    check_readable(model_path);
    impl_ = std::make_unique<Impl>();
    try {
        impl_->env = Ort::Env(ORT_LOGGING_LEVEL_ERROR, "occflownet");
        impl_->session = open_session(impl_->env, model_path, session_options(options));
        impl_->info = check_model(impl_->session, model_path);
        impl_->memory = Ort::MemoryInfo::CreateCpu(OrtArenaAllocator, OrtMemTypeDefault);
    } catch (const Ort::Exception& e) {
        fail(Error::kRuntime, model_path + ": onnxruntime: " + e.what());
    }
}

Runner::~Runner() = default;
Runner::Runner(Runner&&) noexcept = default;
Runner& Runner::operator=(Runner&&) noexcept = default;

const ModelInfo& Runner::info() const { return impl_->info; }

std::string Runner::onnxruntime_version() { return OrtGetApiBase()->GetVersionString(); }

void Runner::run(const std::uint8_t* images, int height, int width, const float* intrinsics, const float* cam2ego,
                 std::uint8_t* occupancy, float* density) {
    if (!impl_) fail(Error::kInvalidArgument, "run() on a moved-from Runner");
    if (!images || !intrinsics || !cam2ego || !occupancy)
        fail(Error::kInvalidArgument, "run(): images, intrinsics, cam2ego and occupancy must not be null");
    if (height < 1 || width < 1)
        fail(Error::kInvalidArgument, "run(): image size " + std::to_string(width) + "x" + std::to_string(height) +
                                          " is not positive");
    const auto& fixed = impl_->info.fixed_image_size;
    if (fixed[0] > 0 && (fixed[0] != height || fixed[1] != width))
        fail(Error::kInvalidArgument, "run(): this model takes " + std::to_string(fixed[1]) + "x" +
                                          std::to_string(fixed[0]) + " images only, got " + std::to_string(width) +
                                          "x" + std::to_string(height));
    Impl::Bound& b = impl_->bound;
    const void* ptrs[5] = {images, intrinsics, cam2ego, occupancy, density};
    bool same = b.height == height && b.width == width && std::equal(ptrs, ptrs + 5, b.ptr);
    try {
        if (!same) {
            b.inputs.clear();
            b.outputs.clear();
            const FrameShape img = frame_shape(contract::kImages, {height, width}),
                             K = frame_shape(contract::kIntrinsics), T = frame_shape(contract::kCam2ego),
                             G = grid_shape(impl_->info.grid);
            const OrtMemoryInfo* mem = impl_->memory;
            b.inputs.push_back(Ort::Value::CreateTensor<std::uint8_t>(mem, const_cast<std::uint8_t*>(images), img.count,
                                                                      img.dims.data(), img.rank));
            b.inputs.push_back(Ort::Value::CreateTensor<float>(mem, const_cast<float*>(intrinsics), K.count,
                                                               K.dims.data(), K.rank));
            b.inputs.push_back(Ort::Value::CreateTensor<float>(mem, const_cast<float*>(cam2ego), T.count,
                                                               T.dims.data(), T.rank));
            b.outputs.push_back(Ort::Value::CreateTensor<std::uint8_t>(mem, occupancy, G.count, G.dims.data(), G.rank));
            if (density)
                b.outputs.push_back(Ort::Value::CreateTensor<float>(mem, density, G.count, G.dims.data(), G.rank));
            std::copy(ptrs, ptrs + 5, b.ptr);
            b.height = height, b.width = width;
        }
        impl_->session.Run(Ort::RunOptions{nullptr}, contract::kInputNames.data(), b.inputs.data(), b.inputs.size(),
                           contract::kOutputNames.data(), b.outputs.data(), b.outputs.size());
    } catch (const Ort::Exception& e) {
        b = Impl::Bound{};  // do not reuse tensors of a failed call
        fail(Error::kRuntime, impl_->info.path + ": inference failed: " + e.what());
    }
}

}  // namespace occflownet

// ------------------------------------------------------------------------------------------- extern "C"
struct occflownet_runner {
    occflownet::Runner runner;
};

namespace {

void set_error(char* err, std::size_t size, const char* message) {
    if (err && size) {
        std::strncpy(err, message, size - 1);
        err[size - 1] = '\0';
    }
}

template <typename F>
int guarded(char* err, std::size_t size, F&& body) {
    try {
        body();
        set_error(err, size, "");
        return OCCFLOWNET_OK;
    } catch (const occflownet::Error& e) {
        set_error(err, size, e.what());
        return int(e.code());
    } catch (const std::exception& e) {
        set_error(err, size, e.what());
        return OCCFLOWNET_RUNTIME;
    } catch (...) {
        set_error(err, size, "unknown error");
        return OCCFLOWNET_RUNTIME;
    }
}

}  // namespace

extern "C" {

int occflownet_runner_create(const char* model_path, const occflownet_options* options, occflownet_runner** out,
                             char* err, size_t err_size) {
    return guarded(err, err_size, [&] {
        if (!model_path || !out) throw occflownet::Error(occflownet::Error::kInvalidArgument, "null argument");
        *out = nullptr;
        occflownet::RunnerOptions opts;
        if (options) {
            opts.intra_op_threads = options->intra_op_threads;
            opts.allow_spinning = options->allow_spinning != 0;
            if (options->execution_provider) opts.execution_provider = options->execution_provider;
            opts.device_id = options->device_id;
        }
        *out = new occflownet_runner{occflownet::Runner(model_path, opts)};
    });
}

void occflownet_runner_destroy(occflownet_runner* runner) { delete runner; }

const char* occflownet_runner_camera(const occflownet_runner* runner, int i) {
    if (!runner || i < 0 || i >= occflownet::kCameras) return nullptr;
    return runner->runner.info().cameras[std::size_t(i)].c_str();
}

size_t occflownet_runner_grid_shape(const occflownet_runner* runner, int shape[3]) {
    if (!runner) return 0;
    const auto& g = runner->runner.info().grid;
    if (shape) std::copy(g.shape.begin(), g.shape.end(), shape);
    return g.voxels();
}

int occflownet_runner_free_index(const occflownet_runner* runner) {
    return runner ? runner->runner.info().free_index : -1;
}

int occflownet_runner_num_classes(const occflownet_runner* runner) {
    return runner ? int(runner->runner.info().classes.size()) : 0;
}

const char* occflownet_runner_class_name(const occflownet_runner* runner, int i) {
    if (!runner || i < 0 || i >= occflownet_runner_num_classes(runner)) return nullptr;
    return runner->runner.info().classes[std::size_t(i)].c_str();
}

int occflownet_runner_default_image_size(const occflownet_runner* runner, int* width, int* height) {
    if (!runner || !width || !height) return OCCFLOWNET_INVALID_ARGUMENT;
    const auto& size = runner->runner.info().default_calibration.image_size[0];
    *width = size[0];
    *height = size[1];
    return OCCFLOWNET_OK;
}

int occflownet_runner_default_calibration(const occflownet_runner* runner, int width, int height, float* intrinsics,
                                          float* cam2ego, char* err, size_t err_size) {
    return guarded(err, err_size, [&] {
        if (!runner || !intrinsics || !cam2ego)
            throw occflownet::Error(occflownet::Error::kInvalidArgument, "null argument");
        const auto& calib = runner->runner.info().default_calibration;
        calib.intrinsics_for_size(width, height, intrinsics);
        calib.cam2ego_f32(cam2ego);
    });
}

int occflownet_calibration_from_json(const occflownet_runner* runner, const char* json_text, int width, int height,
                                     float* intrinsics, float* cam2ego, char* err, size_t err_size) {
    return guarded(err, err_size, [&] {
        if (!runner || !json_text || !intrinsics || !cam2ego)
            throw occflownet::Error(occflownet::Error::kInvalidArgument, "null argument");
        auto calib = occflownet::parse_calibration(json_text, runner->runner.info().cameras);
        calib.intrinsics_for_size(width, height, intrinsics);
        calib.cam2ego_f32(cam2ego);
    });
}

int occflownet_runner_run(occflownet_runner* runner, const uint8_t* images, int height, int width,
                          const float* intrinsics, const float* cam2ego, uint8_t* occupancy, float* density,
                          char* err, size_t err_size) {
    return guarded(err, err_size, [&] {
        if (!runner) throw occflownet::Error(occflownet::Error::kInvalidArgument, "null runner");
        runner->runner.run(images, height, width, intrinsics, cam2ego, occupancy, density);
    });
}

}  // extern "C"
