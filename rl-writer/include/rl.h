/* rl.h: the C ABI of rtvtk's ray recording library.
 *
 * Write mode (record while rendering, Figure 4 of the rtVTK paper):
 *   rl_recorder *rec = rlInit("trace", sizeof(MyPayload));
 *   rlBeginTree(rec, x, y, sample);
 *     rlAddRay(rec, o, d, t, RL_CAMERA, prim, &payload, sizeof payload);
 *     rlDescendTree(rec);  ...children...  rlAscendTree(rec);
 *   rlEndTree(rec);
 *   if (rlFinish(rec) != 0) fprintf(stderr, "%s\n", rlLastError());
 *
 * The current tree is per thread: each tracing thread begins, fills and ends its own trees
 * (several may be open on one thread; calls act on the one begun last).
 * Read mode: rlOpen, then rlReadTree / rlReadRay (reads the current ray and advances),
 * rlNextTree, rlSeekTree, rlResetRead, rlClose.
 *
 * Functions returning int return 0 (or 1 where noted) on success and -1 on error;
 * rlLastError() then describes the error of the calling thread.
 */
#ifndef RL_H
#define RL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

typedef struct rl_recorder rl_recorder;
typedef struct rl_reader rl_reader;

enum {
    RL_CAMERA = 0,
    RL_SHADOW = 1,
    RL_DIFFUSE = 2,
    RL_SPECULAR = 3,
    RL_TRANSMISSION = 4
};

/* Pass as `prim` to rlAddRay for a ray that missed (its t is then ignored). */
#define RL_MISS (-1)

typedef struct {
    uint64_t id;
    uint32_t x, y, sample;
    uint32_t ray_count;
    uint16_t max_depth;
} rl_tree;

typedef struct {
    uint32_t index;     /* index of the ray within its tree */
    int64_t parent;     /* index of the parent ray, -1 for a root */
    uint16_t depth;
    int32_t kind;
    float origin[3];
    float direction[3];
    int32_t hit;        /* 1 when the ray hit something (t is valid) */
    float t;
    int64_t prim;       /* hit primitive, -1 if none */
} rl_ray;

/* Write mode: a new dataset directory at `path` (must not exist or be empty).
 * `payload_size` > 0 declares a fixed-size opaque payload of that many bytes per ray. */
rl_recorder *rlInit(const char *path, size_t payload_size);
/* Registers a ray kind by name; returns its code (>= 16) or -1. */
int32_t rlRegisterKind(rl_recorder *rec, const char *name);
int rlBeginTree(rl_recorder *rec, uint32_t x, uint32_t y, uint32_t sample);
int rlAddRay(rl_recorder *rec, const float origin[3], const float direction[3], float t, int32_t kind,
             int64_t prim, const void *payload, size_t payload_size);
int rlDescendTree(rl_recorder *rec);
int rlAscendTree(rl_recorder *rec);
/* Ends the current tree of this thread; returns its id, or -1. */
int64_t rlEndTree(rl_recorder *rec);
/* The scene, so a viewer can draw the dataset (the `triangles` table): `count` triangles of 9
 * floats each in `vertices` (v0, v1, v2), one material index per triangle in `materials`, and
 * `material_count` materials of 3 floats of diffuse colour (`colors`) and 3 of emission
 * (`emission`), named by `names` (`material_count` strings, or NULL). The triangles whose
 * material emits (any channel > 0) are also written as the `lights` table, so the SQL function
 * `aims_at_light` (the paper's wrong-shadow query) knows the renderer's emitters. */
int rlSetTriangles(rl_recorder *rec, size_t count, const float *vertices, const uint32_t *materials,
                   size_t material_count, const float *colors, const float *emission, const char *const *names);
/* The camera the image was rendered with: position, target, up (3 floats each), vertical field
 * of view in degrees, image size in pixels. Primary ray of film position (px, py), y down:
 * normalize(f + r sx + u sy), f = normalize(target - position), r = normalize(f x up), u = r x f,
 * sx = (2 px / width - 1) tan(fov_y / 2) width / height, sy = (1 - 2 py / height) tan(fov_y / 2). */
int rlSetCamera(rl_recorder *rec, const float position[3], const float target[3], const float up[3], float fov_y,
                uint32_t width, uint32_t height);
/* Seals every ended tree to disk. */
int rlFlush(rl_recorder *rec);
/* Seals everything, frees the recorder, and reports any error of the recording. */
int rlFinish(rl_recorder *rec);

/* Read mode. */
rl_reader *rlOpen(const char *path);
void rlClose(rl_reader *reader);
uint64_t rlTreeCount(rl_reader *reader);
uint64_t rlRayCount(rl_reader *reader);
/* The current tree: 1 when there is one, 0 past the last, -1 on error. */
int rlReadTree(rl_reader *reader, rl_tree *out);
/* The current ray of the current tree, then advances: 1 when read, 0 after the last ray,
 * -1 on error. Copies up to `capacity` bytes of its opaque payload into `payload`. */
int rlReadRay(rl_reader *reader, rl_ray *out, void *payload, size_t capacity);
/* Moves to the next tree: 1 when there is one, 0 past the last, -1 on error. */
int rlNextTree(rl_reader *reader);
/* Moves to the tree with id `id`. */
int rlSeekTree(rl_reader *reader, uint64_t id);
/* Moves within the current tree: the next rlReadRay returns ray `index`. */
int rlSeekRay(rl_reader *reader, uint32_t index);
/* Back to the first ray of the first tree. */
int rlResetRead(rl_reader *reader);

/* The last error of the calling thread (valid until its next rl call), or "" if none. */
const char *rlLastError(void);

#ifdef __cplusplus
}
#endif
#endif
