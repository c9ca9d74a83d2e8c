/* occflownet-c-demo: the C interface in use. Loads a contract-v1 model, prints its cameras and grid, runs one
 * frame of uniform grey images (value 128) at the default calibration's image size, or at W x H with the
 * calibration file given, prints the intrinsics used for the first camera and the occupied voxel count.
 * Usage: occflownet-c-demo model.onnx [calib.json W H]. Exit status 0, or 1 with the library's message on stderr. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "occflownet/runner.h"

int main(int argc, char** argv) {
    char err[1024];
    occflownet_runner* runner = NULL;
    if (argc != 2 && argc != 5) {
        fprintf(stderr, "usage: %s model.onnx [calib.json W H]\n", argv[0]);
        return 2;
    }
    if (occflownet_runner_create(argv[1], NULL, &runner, err, sizeof err) != OCCFLOWNET_OK) {
        fprintf(stderr, "occflownet-c-demo: %s\n", err);
        return 1;
    }
    int shape[3], dw = 0, dh = 0;
    size_t voxels = occflownet_runner_grid_shape(runner, shape);
    occflownet_runner_default_image_size(runner, &dw, &dh);
    int width = dw, height = dh;
    char* calib_text = NULL;
    if (argc == 5) {  /* the whole calibration file as one string */
        FILE* f = fopen(argv[2], "rb");
        long n = -1;
        if (f && fseek(f, 0, SEEK_END) == 0) n = ftell(f);
        if (n >= 0 && fseek(f, 0, SEEK_SET) == 0 && (calib_text = calloc((size_t)n + 1, 1)) != NULL &&
            fread(calib_text, 1, (size_t)n, f) != (size_t)n) {
            free(calib_text);
            calib_text = NULL;
        }
        if (f) fclose(f);
        if (!calib_text) {
            fprintf(stderr, "occflownet-c-demo: cannot read %s\n", argv[2]);
            occflownet_runner_destroy(runner);
            return 1;
        }
        width = atoi(argv[3]);
        height = atoi(argv[4]);
    }
    printf("cameras:");
    for (int i = 0; i < 6; ++i) printf(" %s", occflownet_runner_camera(runner, i));
    printf("\ngrid: %d x %d x %d, free index %d (%s), default image size %dx%d\n", shape[0], shape[1], shape[2],
           occflownet_runner_free_index(runner),
           occflownet_runner_class_name(runner, occflownet_runner_free_index(runner)), dw, dh);

    size_t n_img = (size_t)6 * height * width * 3;
    unsigned char* images = malloc(n_img);
    unsigned char* occupancy = malloc(voxels);
    float* density = malloc(voxels * sizeof(float));
    float intrinsics[6 * 9], cam2ego[6 * 16];
    int rc = 1;
    if (!images || !occupancy || !density) {
        fprintf(stderr, "occflownet-c-demo: out of memory\n");
        goto done;
    }
    memset(images, 128, n_img);
    int status = calib_text ? occflownet_calibration_from_json(runner, calib_text, width, height, intrinsics, cam2ego,
                                                                err, sizeof err)
                            : occflownet_runner_default_calibration(runner, width, height, intrinsics, cam2ego, err,
                                                                    sizeof err);
    if (status == OCCFLOWNET_OK)
        printf("%s intrinsics for %dx%d: fx %.6f fy %.6f cx %.6f cy %.6f\n", occflownet_runner_camera(runner, 0),
               width, height, intrinsics[0], intrinsics[4], intrinsics[2], intrinsics[5]);
    if (status != OCCFLOWNET_OK ||
        occflownet_runner_run(runner, images, height, width, intrinsics, cam2ego, occupancy, density, err,
                              sizeof err)) {
        fprintf(stderr, "occflownet-c-demo: %s\n", err);
        goto done;
    }
    size_t occupied = 0;
    for (size_t i = 0; i < voxels; ++i) occupied += occupancy[i] != occflownet_runner_free_index(runner);
    printf("occupied voxels: %zu of %zu\n", occupied, voxels);
    rc = 0;
done:
    free(calib_text);
    free(images);
    free(occupancy);
    free(density);
    occflownet_runner_destroy(runner);
    return rc;
}
