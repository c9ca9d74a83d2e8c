// See frame_io.hpp. libjpeg reports errors through longjmp: the decoding functions below keep only trivially
// destructible locals between setjmp and the end of decompression, and throw after the jump has landed.
#include "frame_io.hpp"

#include "occflownet/runner.hpp"

#include <algorithm>
#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <future>
#include <iterator>
#include <sys/stat.h>

#include <jpeglib.h>
#include <png.h>

namespace occflownet::io {
namespace {

[[noreturn]] void fail(Error::Code code, const std::string& message) { throw Error(code, message); }

bool is_file(const std::string& path) {
    struct stat st {};
    return ::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode);
}

bool is_dir(const std::string& path) {
    struct stat st {};
    return ::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode);
}

// ---- libjpeg error manager: errors and warnings both end the decode with a message
struct JpegErr {
    jpeg_error_mgr mgr;
    std::jmp_buf jump;
    char message[JMSG_LENGTH_MAX];
};

void jpeg_error_exit(j_common_ptr cinfo) {
    auto* e = reinterpret_cast<JpegErr*>(cinfo->err);
    (*cinfo->err->format_message)(cinfo, e->message);
    std::longjmp(e->jump, 1);
}

void jpeg_emit(j_common_ptr cinfo, int level) {
    if (level < 0) jpeg_error_exit(cinfo);  // a warning: corrupt or truncated data
}

// Decodes (dst != nullptr) or only reads the header; returns "" or the error message.
std::string jpeg_run(const EncodedImage& im, std::uint8_t* dst, int* width, int* height, int reduction = 1) {
    jpeg_decompress_struct cinfo;
    JpegErr err;
    std::memset(&cinfo, 0, sizeof cinfo);
    cinfo.err = jpeg_std_error(&err.mgr);
    err.mgr.error_exit = jpeg_error_exit;
    err.mgr.emit_message = jpeg_emit;
    err.message[0] = '\0';
    if (setjmp(err.jump)) {
        jpeg_destroy_decompress(&cinfo);
        return err.message[0] ? err.message : "undecodable JPEG";
    }
    jpeg_create_decompress(&cinfo);
    jpeg_mem_src(&cinfo, im.bytes.data(), static_cast<unsigned long>(im.bytes.size()));
    jpeg_read_header(&cinfo, TRUE);
    *width = int(cinfo.image_width);
    *height = int(cinfo.image_height);
    if (dst) {
        if (cinfo.jpeg_color_space == JCS_CMYK || cinfo.jpeg_color_space == JCS_YCCK) {
            jpeg_destroy_decompress(&cinfo);
            return "CMYK/YCCK JPEGs are not supported (convert to RGB)";
        }
        cinfo.out_color_space = JCS_RGB;  // grey -> RGB as OpenCV's IMREAD_COLOR (then BGR -> RGB)
        cinfo.scale_num = 1;              // DCT scaling, as OpenCV's IMREAD_REDUCED_COLOR_n
        cinfo.scale_denom = unsigned(reduction);
        jpeg_start_decompress(&cinfo);
        if (int(cinfo.output_width) != (*width + reduction - 1) / reduction ||
            int(cinfo.output_height) != (*height + reduction - 1) / reduction) {
            jpeg_destroy_decompress(&cinfo);
            return "unexpected size at reduced scale";
        }
        const std::size_t stride = std::size_t(cinfo.output_width) * 3;
        while (cinfo.output_scanline < cinfo.output_height) {
            JSAMPROW row = dst + std::size_t(cinfo.output_scanline) * stride;
            jpeg_read_scanlines(&cinfo, &row, 1);
        }
        jpeg_finish_decompress(&cinfo);  // reads to EOI: a truncated file warns here
    }
    jpeg_destroy_decompress(&cinfo);
    return "";
}

}  // namespace

std::vector<std::uint8_t> read_file(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in || !is_file(path)) fail(Error::kIO, "file not found or unreadable: " + path);
    std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    if (in.bad()) fail(Error::kIO, "error reading " + path);
    return bytes;
}

std::string read_text(const std::string& path, std::size_t max_bytes) {
    struct stat st {};
    if (::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode) && std::size_t(st.st_size) > max_bytes)
        fail(Error::kInvalidArgument, path + " is " + std::to_string(st.st_size) + " bytes, over the limit of " +
                                          std::to_string(max_bytes) + " bytes");
    auto bytes = read_file(path);
    return std::string(bytes.begin(), bytes.end());
}

std::vector<std::string> find_camera_images(const std::string& folder, const std::vector<std::string>& cameras) {
    if (!is_dir(folder)) fail(Error::kIO, "image folder not found: " + folder);
    std::vector<std::string> found, missing;
    for (const std::string& cam : cameras) {
        std::string hit;
        for (const char* suffix : {".jpg", ".jpeg", ".png"})
            if (hit.empty() && is_file(folder + "/" + cam + suffix)) hit = folder + "/" + cam + suffix;
        if (hit.empty()) missing.push_back(cam + ".jpg");
        found.push_back(hit);
    }
    if (!missing.empty()) {
        std::string m, need;
        for (auto& s : missing) m += (m.empty() ? "" : ", ") + s;
        for (auto& c : cameras) need += (need.empty() ? "" : ", ") + c + ".jpg";
        fail(Error::kIO, folder + ": missing camera images " + m + " (need one file per camera: " + need + ")");
    }
    return found;
}

EncodedImage probe_image(const std::string& path) {
    EncodedImage im;
    im.name = path;
    im.bytes = read_file(path);
    const auto& b = im.bytes;
    static const std::uint8_t png_sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
    if (b.size() >= 8 && std::memcmp(b.data(), png_sig, 8) == 0) {
        im.png = true;
        png_image png;
        std::memset(&png, 0, sizeof png);
        png.version = PNG_IMAGE_VERSION;
        if (!png_image_begin_read_from_memory(&png, b.data(), b.size()))
            fail(Error::kInvalidArgument, path + ": not a decodable PNG image (" + png.message + ")");
        im.width = int(png.width);
        im.height = int(png.height);
        png_image_free(&png);
    } else if (b.size() >= 3 && b[0] == 0xFF && b[1] == 0xD8 && b[2] == 0xFF) {
        std::string msg = jpeg_run(im, nullptr, &im.width, &im.height);
        if (!msg.empty()) fail(Error::kInvalidArgument, path + ": not a decodable JPEG image (" + msg + ")");
    } else {
        fail(Error::kInvalidArgument, path + ": not a JPEG or PNG image");
    }
    if (im.width < 1 || im.height < 1) fail(Error::kInvalidArgument, path + ": image has no pixels");
    return im;
}

int decode_reduction(const EncodedImage& im, const std::array<int, 2>& input_size) {
    if (im.png) return 1;
    // decode_reduction of occflownet/contract/images.py: the largest n whose decoded image (ceil(W/n) x ceil(H/n))
    // still holds a crop window (crop_window there) of at least the network input
    const long long h_in = input_size[0], w_in = input_size[1];
    int n = 1;
    for (int candidate : {2, 4, 8}) {
        const long long w = (im.width + candidate - 1) / candidate, h = (im.height + candidate - 1) / candidate;
        const long long crop_w = std::min(w, (2 * h * w_in + h_in) / (2 * h_in));
        const long long crop_h = std::min(h, (2 * w * h_in + w_in) / (2 * w_in));
        if (crop_w >= w_in && crop_h >= h_in) n = candidate;
    }
    return n;
}

void decode_into(const EncodedImage& im, std::uint8_t* dst, int reduction) {
    if (!im.png) {
        int w = 0, h = 0;
        std::string msg = jpeg_run(im, dst, &w, &h, reduction);
        if (!msg.empty()) fail(Error::kInvalidArgument, im.name + ": corrupt JPEG (" + msg + ")");
        return;
    }
    if (reduction != 1) fail(Error::kInvalidArgument, im.name + ": PNGs are decoded whole (reduction 1)");
    png_image png;
    std::memset(&png, 0, sizeof png);
    png.version = PNG_IMAGE_VERSION;
    if (!png_image_begin_read_from_memory(&png, im.bytes.data(), im.bytes.size()))
        fail(Error::kInvalidArgument, im.name + ": corrupt PNG (" + png.message + ")");
    if (png.format & PNG_FORMAT_FLAG_LINEAR) {
        png_image_free(&png);
        fail(Error::kInvalidArgument, im.name + ": 16-bit PNGs are not supported (use 8 bits per channel)");
    }
    const bool alpha = (png.format & PNG_FORMAT_FLAG_ALPHA) != 0;
    png.format = alpha ? PNG_FORMAT_RGBA : PNG_FORMAT_RGB;
    std::vector<std::uint8_t> rgba;
    if (alpha) rgba.resize(std::size_t(png.width) * png.height * 4);
    if (!png_image_finish_read(&png, nullptr, alpha ? rgba.data() : dst, 0, nullptr))
        fail(Error::kInvalidArgument, im.name + ": corrupt PNG (" + png.message + ")");
    if (alpha)  // drop alpha, as OpenCV's IMREAD_COLOR
        for (std::size_t i = 0, n = std::size_t(png.width) * png.height; i < n; ++i)
            std::memcpy(dst + 3 * i, rgba.data() + 4 * i, 3);
}

void write_npy(const std::string& path, const std::string& dtype, const std::vector<std::size_t>& shape,
               const void* data, std::size_t nbytes) {
    std::string dims;
    for (std::size_t i = 0; i < shape.size(); ++i) dims += (i ? ", " : "") + std::to_string(shape[i]);
    if (shape.size() == 1) dims += ",";
    std::string header = "{'descr': '" + dtype + "', 'fortran_order': False, 'shape': (" + dims + "), }";
    std::size_t total = 10 + header.size() + 1;
    header.append((64 - total % 64) % 64, ' ');
    header += '\n';
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    if (!out) fail(Error::kIO, "cannot write " + path);
    const char magic[8] = {'\x93', 'N', 'U', 'M', 'P', 'Y', 1, 0};
    const std::uint16_t len = std::uint16_t(header.size());
    const char len_le[2] = {char(len & 0xFF), char(len >> 8)};
    out.write(magic, 8).write(len_le, 2).write(header.data(), std::streamsize(header.size()));
    out.write(static_cast<const char*>(data), std::streamsize(nbytes));
    if (!out) fail(Error::kIO, "error writing " + path);
}

void decode_all_into(const std::vector<EncodedImage>& images, std::uint8_t* dst, std::size_t frame_bytes,
                     int reduction) {
    std::vector<std::future<void>> jobs;
    jobs.reserve(images.size());
    for (std::size_t c = 0; c < images.size(); ++c)
        jobs.push_back(std::async(std::launch::async, [&images, dst, frame_bytes, reduction, c] {
            decode_into(images[c], dst + c * frame_bytes, reduction);
        }));
    for (auto& job : jobs) job.wait();   // every thread done before an error leaves this frame
    for (auto& job : jobs) job.get();    // rethrows the first camera's error
}

}  // namespace occflownet::io
