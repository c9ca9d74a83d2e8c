// File I/O of the occflownet-run program: camera image folders, JPEG/PNG decoding (libjpeg-turbo, libpng) straight
// into the [6, H, W, 3] input slab, calibration files, and .npy output. Errors are occflownet::Error.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace occflownet::io {

std::vector<std::uint8_t> read_file(const std::string& path);   // Error(kIO) naming the file
// A text file of at most max_bytes: Error(kInvalidArgument) naming the file and its size when it is larger (checked
// before it is read).
std::string read_text(const std::string& path, std::size_t max_bytes);

// <folder>/<camera>.jpg (or .jpeg, .png; first found) per camera, in `cameras` order; Error listing what is missing.
std::vector<std::string> find_camera_images(const std::string& folder, const std::vector<std::string>& cameras);

// An encoded image in memory: its size from the header, without decoding.
struct EncodedImage {
    std::string name;                 // for messages (the path)
    std::vector<std::uint8_t> bytes;
    bool png = false;
    int width = 0, height = 0;
};
EncodedImage probe_image(const std::string& path);   // reads the file; Error if not a readable JPEG/PNG header

// Decodes `image` into dst, uint8 [height, width, 3] RGB (image.height x image.width). JPEG: libjpeg-turbo with its
// defaults (islow DCT, fancy upsampling), as OpenCV's decoder; any libjpeg warning (corrupt or truncated data) is an
// Error. PNG: 8-bit grey/RGB/palette, alpha dropped; 16-bit PNGs are refused. EXIF orientation is ignored.
// reduction n > 1 (JPEG only): decoded at 1/n by libjpeg's DCT scaling (scale_num 1, scale_denom n), as OpenCV's
// IMREAD_REDUCED_COLOR_n: dst is then uint8 [ceil(height / n), ceil(width / n), 3].
void decode_into(const EncodedImage& image, std::uint8_t* dst, int reduction = 1);

// Decodes images[c] into dst + c * frame_bytes (as decode_into, each at `reduction`), every image in its own thread
// (libjpeg and libpng keep their state per call); all threads are joined, then the first camera's error, in camera
// order, is thrown.
void decode_all_into(const std::vector<EncodedImage>& images, std::uint8_t* dst, std::size_t frame_bytes,
                     int reduction = 1);

// The scale 1/n a JPEG is decoded at for a model whose network input is input_size [H, W]: the contract's rule
// (occflownet/contract/images.py, decode_reduction): the largest of 1, 2, 4, 8 whose decoded image still holds a
// crop window (crop_window) of at least the network input; always 1 for a PNG.
int decode_reduction(const EncodedImage& image, const std::array<int, 2>& input_size);

// Writes a NumPy .npy (format 1.0, C order) of `dtype` ("|u1" or "<f4") and `shape`.
void write_npy(const std::string& path, const std::string& dtype, const std::vector<std::size_t>& shape,
               const void* data, std::size_t nbytes);

}  // namespace occflownet::io
