/* A small recursive Whitted-style tracer instrumented with rl (the paper's Figure 4 pattern),
 * then a read-mode pass over what it recorded. Usage: tracer DATASET
 * Prints "recorded T R" and "read T R" (trees, rays); exits non-zero on any error. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "rl.h"

typedef struct { float throughput[3]; int32_t bounce; } Payload;

static const float sphere_c[2][3] = {{-0.5f, 0.0f, -3.0f}, {0.7f, 0.1f, -2.5f}};
static const float sphere_r[2] = {0.6f, 0.4f};
static const float light[3] = {2.0f, 3.0f, 0.0f};
static long rays_added = 0;

static int fail(const char *what) {
    fprintf(stderr, "%s failed: %s\n", what, rlLastError());
    exit(1);
}

static float dot(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* Nearest hit: returns the sphere index or -1 (floor plane y = -1 is index 2). */
static int intersect(const float *o, const float *d, float *t_out) {
    int best = -1;
    float best_t = 1e30f;
    for (int i = 0; i < 2; i++) {
        float oc[3] = {o[0] - sphere_c[i][0], o[1] - sphere_c[i][1], o[2] - sphere_c[i][2]};
        float b = dot(oc, d), c = dot(oc, oc) - sphere_r[i] * sphere_r[i], disc = b * b - c;
        if (disc < 0) continue;
        float t = -b - sqrtf(disc);
        if (t < 1e-3f) t = -b + sqrtf(disc);
        if (t > 1e-3f && t < best_t) { best_t = t; best = i; }
    }
    if (d[1] < 0) {
        float t = (-1.0f - o[1]) / d[1];
        if (t > 1e-3f && t < best_t) { best_t = t; best = 2; }
    }
    *t_out = best_t;
    return best;
}

static void trace(rl_recorder *rec, const float *o, const float *d, int kind, int depth, float weight) {
    float t;
    int hit = intersect(o, d, &t);
    Payload p = {{weight, weight * 0.5f, weight * 0.25f}, depth};
    if (rlAddRay(rec, o, d, t, kind, hit < 0 ? RL_MISS : hit, &p, sizeof p) != 0) fail("rlAddRay");
    rays_added++;
    if (hit < 0 || depth >= 3) return;
    float x[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
    float n[3];
    if (hit == 2) { n[0] = 0; n[1] = 1; n[2] = 0; }
    else for (int k = 0; k < 3; k++) n[k] = (x[k] - sphere_c[hit][k]) / sphere_r[hit];
    if (rlDescendTree(rec) != 0) fail("rlDescendTree");
    /* Shadow ray to the point light. */
    float l[3] = {light[0] - x[0], light[1] - x[1], light[2] - x[2]};
    float len = sqrtf(dot(l, l));
    for (int k = 0; k < 3; k++) l[k] /= len;
    float st;
    int occ = intersect(x, l, &st);
    Payload sp = {{0, 0, 0}, depth + 1};
    if (rlAddRay(rec, x, l, st, RL_SHADOW, occ < 0 ? RL_MISS : occ, &sp, sizeof sp) != 0) fail("rlAddRay");
    rays_added++;
    /* Mirror reflection. */
    float r[3], dn = dot(d, n);
    for (int k = 0; k < 3; k++) r[k] = d[k] - 2 * dn * n[k];
    trace(rec, x, r, RL_SPECULAR, depth + 1, weight * 0.8f);
    if (rlAscendTree(rec) != 0) fail("rlAscendTree");
}

int main(int argc, char **argv) {
    if (argc < 2) return 2;
    rl_recorder *rec = rlInit(argv[1], sizeof(Payload));
    if (!rec) fail("rlInit");
    /* Misuse is reported, not fatal. */
    if (rlAddRay(rec, light, light, 1.0f, RL_CAMERA, 0, NULL, 0) == 0) { fprintf(stderr, "expected an error\n"); return 1; }
    if (strstr(rlLastError(), "rlBeginTree") == NULL) { fprintf(stderr, "bad message: %s\n", rlLastError()); return 1; }
    const int W = 16, H = 12;
    /* The scene for viewers: a floor quad (two triangles) of one grey material, and the camera. */
    const float quad[18] = {-5, -1, -1, 5, -1, -1, 5, -1, -9, -5, -1, -1, 5, -1, -9, -5, -1, -9};
    const uint32_t mats[2] = {0, 0};
    const float grey[3] = {0.7f, 0.7f, 0.7f}, black[3] = {0, 0, 0};
    const char *names[1] = {"floor"};
    const uint32_t bad_mats[2] = {0, 3};
    if (rlSetTriangles(rec, 2, quad, bad_mats, 1, grey, black, names) == 0) { fprintf(stderr, "expected a material error\n"); return 1; }
    if (strstr(rlLastError(), "material 3") == NULL) { fprintf(stderr, "bad message: %s\n", rlLastError()); return 1; }
    if (rlSetTriangles(rec, 2, quad, mats, 1, grey, black, names) != 0) fail("rlSetTriangles");
    const float eye[3] = {0, 0, 0}, at[3] = {0, 0, -1}, up[3] = {0, 1, 0};
    if (rlSetCamera(rec, eye, eye, up, 60.0f, W, H) == 0) { fprintf(stderr, "expected a camera error\n"); return 1; }
    if (rlSetCamera(rec, eye, at, up, 60.0f, W, H) != 0) fail("rlSetCamera");
    long trees = 0;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            if (rlBeginTree(rec, x, y, 0) != 0) fail("rlBeginTree");
            float o[3] = {0, 0, 0};
            float d[3] = {(x - W / 2) / (float)W, (H / 2 - y) / (float)H, -1};
            float len = sqrtf(dot(d, d));
            for (int k = 0; k < 3; k++) d[k] /= len;
            trace(rec, o, d, RL_CAMERA, 0, 1.0f);
            if (rlEndTree(rec) < 0) fail("rlEndTree");
            trees++;
        }
    if (rlFinish(rec) != 0) fail("rlFinish");
    printf("recorded %ld %ld\n", trees, rays_added);

    rl_reader *rd = rlOpen(argv[1]);
    if (!rd) fail("rlOpen");
    if ((long)rlTreeCount(rd) != trees || (long)rlRayCount(rd) != rays_added) { fprintf(stderr, "counts differ\n"); return 1; }
    long read_trees = 0, read_rays = 0;
    rl_tree tr;
    while (rlReadTree(rd, &tr) == 1) {
        rl_ray ray;
        Payload p;
        uint32_t n = 0;
        int rc;
        while ((rc = rlReadRay(rd, &ray, &p, sizeof p)) == 1) {
            if (ray.index != n) { fprintf(stderr, "ray order\n"); return 1; }
            if (p.bounce != ray.depth) { fprintf(stderr, "payload bounce %d != depth %d\n", p.bounce, ray.depth); return 1; }
            if ((ray.parent < 0) != (ray.depth == 0)) { fprintf(stderr, "root mismatch\n"); return 1; }
            if (ray.hit != (ray.prim >= 0)) { fprintf(stderr, "hit mismatch\n"); return 1; }
            n++;
        }
        if (rc < 0) fail("rlReadRay");
        if (n != tr.ray_count) { fprintf(stderr, "tree %llu: %u rays read, %u listed\n", (unsigned long long)tr.id, n, tr.ray_count); return 1; }
        read_trees++;
        read_rays += n;
        if (rlNextTree(rd) < 0) fail("rlNextTree");
    }
    if (rlSeekTree(rd, 5) != 0 || rlReadTree(rd, &tr) != 1 || tr.id != 5 || tr.x != 5) fail("rlSeekTree");
    if (rlSeekTree(rd, 100000) == 0) { fprintf(stderr, "seek to a missing tree succeeded\n"); return 1; }
    rlClose(rd);
    if (rlOpen("/nonexistent/trace") != NULL || strstr(rlLastError(), "manifest") == NULL) { fprintf(stderr, "open error: %s\n", rlLastError()); return 1; }
    printf("read %ld %ld\n", read_trees, read_rays);
    return 0;
}
