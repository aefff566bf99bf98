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

/* Element types of typed payload columns (rl_column.type). */
enum {
    RL_F32 = 1,
    RL_F64 = 2,
    RL_I32 = 3,
    RL_U32 = 4,
    RL_I64 = 5,
    RL_U64 = 6,
    RL_U8 = 7,
    RL_U16 = 8
};

/* A typed payload column: `count` values of `type` per ray (3 x RL_F32 is a vec3). The name is
 * copied; it becomes a column of the `rays` table (SQL: `SELECT throughput FROM rays`). */
typedef struct {
    const char *name;
    int32_t type;
    uint32_t count;
} rl_column;

/* rlInitColumns / rlInitImmediate flag: record where each ray was added (the `site` column, the
 * `sites` table; SQL shows `file:line function`). */
#define RL_RECORD_SITES 1u

/* rlSetCameraMatrix's field-of-view axis. */
enum { RL_FOV_X = 0, RL_FOV_Y = 1 };

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
/* Write mode with typed payload: `column_count` columns (names distinct; copied), then
 * `bytes_size` opaque bytes per ray (0: none). rlAddRay's payload is then one packed row: each
 * column's values in order, native byte order, no padding between them (a
 * `#pragma pack(1)` struct, or memcpy into a buffer), then the opaque bytes;
 * rlPayloadRowSize gives its size. `flags`: 0, or RL_RECORD_SITES to record each ray's site
 * (see RL_ADD_RAY). NULL (rlLastError says why) for a bad type, a zero count, a duplicate name
 * or an unknown flag. */
rl_recorder *rlInitColumns(const char *path, const rl_column *columns, size_t column_count, size_t bytes_size,
                           uint32_t flags);
/* Bytes of one packed payload row of this recorder (typed columns, then opaque bytes). */
int64_t rlPayloadRowSize(rl_recorder *rec);
/* Immediate mode: the recording stays in memory (no directory), its oldest trees evicted past
 * `memory_budget` bytes (0: 256 MiB). Columns and payload rows as for rlInitColumns. Read it
 * while recording with rlOpenRecording; rlFinish frees it. */
rl_recorder *rlInitImmediate(const rl_column *columns, size_t column_count, size_t bytes_size, size_t memory_budget,
                             uint32_t flags);
/* A read cursor over an immediate-mode recording while it records (from any thread): it sees
 * every tree ended before each read; rlTreeCount and rlRayCount give the counts now. Close it
 * with rlClose before rlFinish frees the recording. NULL for a write-mode recorder. */
rl_reader *rlOpenRecording(rl_recorder *rec);
/* Registers a ray kind by name; returns its code (>= 16) or -1. */
int32_t rlRegisterKind(rl_recorder *rec, const char *name);
int rlBeginTree(rl_recorder *rec, uint32_t x, uint32_t y, uint32_t sample);
/* Adds a ray to the current tree of this thread, as a child of the ray the last rlDescendTree
 * went into (a root before). `t` is the hit distance in multiples of `direction` (world units
 * for a unit direction), used when `prim` >= 0; `prim` RL_MISS for a miss. `payload` is one
 * packed row of rlPayloadRowSize bytes (or NULL with 0: no payload, the columns null); a row
 * of another size is refused. Copies everything; safe from many threads at once. */
int rlAddRay(rl_recorder *rec, const float origin[3], const float direction[3], float t, int32_t kind,
             int64_t prim, const void *payload, size_t payload_size);
/* rlAddRay, naming its call site (`file` and `function` NUL-terminated, copied; `function` may
 * be NULL). Recorded when the recorder records sites (RL_RECORD_SITES); ignored otherwise.
 * RL_ADD_RAY passes the caller's __FILE__, __LINE__ and __func__. */
int rlAddRayAt(rl_recorder *rec, const float origin[3], const float direction[3], float t, int32_t kind, int64_t prim,
               const void *payload, size_t payload_size, const char *file, uint32_t line, const char *function);
#define RL_ADD_RAY(rec, origin, direction, t, kind, prim, payload, payload_size) \
    rlAddRayAt(rec, origin, direction, t, kind, prim, payload, payload_size, __FILE__, __LINE__, __func__)
int rlDescendTree(rl_recorder *rec);
int rlAscendTree(rl_recorder *rec);
/* Ends the current tree of this thread; returns its id, or -1. */
int64_t rlEndTree(rl_recorder *rec);
/* The scene, so a viewer can draw the dataset (the `triangles` table): `count` triangles of 9
 * floats each in `vertices` (v0, v1, v2), one material index per triangle in `materials`, and
 * `material_count` materials of 3 floats of diffuse colour (`colors`) and 3 of emission
 * (`emission`), named by `names` (`material_count` strings, or NULL). The triangles whose
 * material emits (any channel > 0) are also the `lights` table (written at the next rlFlush or
 * rlFinish, with rlSetPointLights' lights), so the SQL function `aims_at_light` (the paper's
 * wrong-shadow query) knows the renderer's emitters. Copies everything. */
int rlSetTriangles(rl_recorder *rec, size_t count, const float *vertices, const uint32_t *materials,
                   size_t material_count, const float *colors, const float *emission, const char *const *names);
/* The camera the image was rendered with: position, target, up (3 floats each), vertical field
 * of view in degrees, image size in pixels. Primary ray of film position (px, py), y down:
 * normalize(f + r sx + u sy), f = normalize(target - position), r = normalize(f x up), u = r x f,
 * sx = (2 px / width - 1) tan(fov_y / 2) width / height, sy = (1 - 2 py / height) tan(fov_y / 2). */
int rlSetCamera(rl_recorder *rec, const float position[3], const float target[3], const float up[3], float fov_y,
                uint32_t width, uint32_t height);
/* Point lights (beside the emissive triangles of rlSetTriangles, which are lights already):
 * `count` positions and RGB intensities, 3 floats each, finite, intensities >= 0. They replace
 * the point lights set before. A point light is a row of the `lights` table whose three
 * vertices are its position; `aims_at_light` accepts a ray within 1e-5 rad of it. The `lights`
 * table is written at the next rlFlush or rlFinish. */
int rlSetPointLights(rl_recorder *rec, size_t count, const float *positions, const float *intensities);
/* The camera as a 4x4 camera-to-world matrix (16 floats, row-major; its last column the
 * position, its columns 0-2 the camera's x, y, z axes in world space), with +y up and the view
 * along +z (`forward_z` = 1, pbrt and Mitsuba) or -z (-1, OpenGL); `fov` in degrees across the
 * RL_FOV_X or RL_FOV_Y axis; the image size. Stored as rlSetCamera's look-at camera, whose
 * right is forward x up: a camera whose x axis points the other way (pbrt's left-handed
 * camera space) negates its x column first. */
int rlSetCameraMatrix(rl_recorder *rec, const float camera_to_world[16], float forward_z, float fov, int32_t fov_axis,
                      uint32_t width, uint32_t height);
/* A renderer's BVH node: its parent's index (-1 for the root), bounds, and for a leaf its
 * triangles, prims[first_prim .. first_prim + prim_count) of rlSetBvh's `prims` (an inner node
 * has prim_count 0). */
typedef struct {
    int64_t parent;
    float min[3];
    float max[3];
    uint32_t first_prim;
    uint32_t prim_count;
} rl_bvh_node;
/* The renderer's BVH as the `bvh_nodes` table (node ids are indices into `nodes`; levels are
 * counted from the parents): `rtvtk analyze bvh` and the viewer's BVH layer read it. Copies. */
int rlSetBvh(rl_recorder *rec, size_t node_count, const rl_bvh_node *nodes, size_t prim_count, const uint32_t *prims);
/* The BVH nodes the last ray added on this thread visited, in order (the `ray_nodes` table):
 * `leaf_hit` per node 1 (a triangle of the leaf was hit), 0 (none was), -1 (an inner node), or
 * NULL when not known. Written at rlFlush / rlFinish. */
int rlAddRayVisits(rl_recorder *rec, size_t count, const uint32_t *nodes, const int8_t *leaf_hit);
/* Seals every ended tree to disk (and the lights table, if it changed). */
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
