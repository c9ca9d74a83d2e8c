/* occflownet embedding runtime, C interface over the C++ Runner (occflownet/runner.hpp).
 *
 * Every function returns OCCFLOWNET_OK (0) or an error code and, when err is not NULL, writes a NUL-terminated
 * message (truncated to err_size bytes) naming the file, camera or field. Nothing aborts or throws across this
 * interface. Arrays are C order; shapes as in runner.hpp:
 *   images uint8 [6, height, width, 3] RGB (model camera order), intrinsics float32 [6, 3, 3] for that size,
 *   cam2ego float32 [6, 4, 4], occupancy uint8 [X, Y, Z], density float32 [X, Y, Z] (X, Y, Z = grid shape). */
#ifndef OCCFLOWNET_RUNNER_H
#define OCCFLOWNET_RUNNER_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

enum {
    OCCFLOWNET_OK = 0,
    OCCFLOWNET_INVALID_ARGUMENT = 1,
    OCCFLOWNET_CONTRACT = 2,   /* the model file breaks ONNX contract v1 */
    OCCFLOWNET_RUNTIME = 3,    /* onnxruntime failed */
    OCCFLOWNET_IO = 4          /* a file could not be read */
};

typedef struct occflownet_runner occflownet_runner;

typedef struct {
    int intra_op_threads;            /* 0: onnxruntime's default */
    int allow_spinning;              /* 0 or 1 */
    const char* execution_provider;  /* NULL or "cpu", "cuda", ... */
    int device_id;
} occflownet_options;

/* Load a contract-v1 model. options may be NULL (defaults). On success *out owns the runner. */
int occflownet_runner_create(const char* model_path, const occflownet_options* options, occflownet_runner** out,
                             char* err, size_t err_size);
void occflownet_runner_destroy(occflownet_runner* runner);

/* Camera i (0..5) name in input order, or NULL. Valid as long as the runner. */
const char* occflownet_runner_camera(const occflownet_runner* runner, int i);
/* Grid shape [X, Y, Z] into shape[3]; returns X*Y*Z (0 if runner is NULL). */
size_t occflownet_runner_grid_shape(const occflownet_runner* runner, int shape[3]);
int occflownet_runner_free_index(const occflownet_runner* runner);
/* Number of classes and class i's name (NULL if out of range). */
int occflownet_runner_num_classes(const occflownet_runner* runner);
const char* occflownet_runner_class_name(const occflownet_runner* runner, int i);
/* The default calibration's image size [w, h] of camera 0. */
int occflownet_runner_default_image_size(const occflownet_runner* runner, int* width, int* height);

/* The model's default calibration for images of width x height: intrinsics float32 [6,3,3], cam2ego [6,4,4]. */
int occflownet_runner_default_calibration(const occflownet_runner* runner, int width, int height, float* intrinsics,
                                          float* cam2ego, char* err, size_t err_size);
/* A calibration JSON text for this model's cameras, for images of width x height (rescaled as in runner.hpp). */
int occflownet_calibration_from_json(const occflownet_runner* runner, const char* json_text, int width, int height,
                                     float* intrinsics, float* cam2ego, char* err, size_t err_size);

/* One frame; density may be NULL. */
int occflownet_runner_run(occflownet_runner* runner, const uint8_t* images, int height, int width,
                          const float* intrinsics, const float* cam2ego, uint8_t* occupancy, float* density,
                          char* err, size_t err_size);

#ifdef __cplusplus
}
#endif
#endif
