// A small C++ path tracer that records everything a dataset can hold through rl.h, as a
// third-party renderer would: typed payload columns (a vec3, a u32, a u8, an f64) and opaque
// bytes, the scene's triangles with an emissive quad, a point light, its BVH and the nodes each
// closest-hit ray visited, every ray's call site, the camera as a
// camera-to-world matrix (OpenGL convention, looking along -z), several tracing threads, an
// immediate-mode recording read while it records, and rlLastError for every refusal. `--bug` aims the point light's shadow rays from the floor at
// its mirror image below the floor (the paper's wrong-shadow bug).
//
//   c++ -std=c++17 -O2 -I rl-writer/include rl-writer/examples/cpp_tracer.cpp
//       target/debug/librl.a -lpthread -ldl -lm -o cpp_tracer
//   ./cpp_tracer OUT [--bug]       # prints its ray counts by kind; then `rtvtk view OUT`

#include <rl.h>

#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <vector>

namespace {

using Vec = std::array<float, 3>;
Vec operator+(Vec a, Vec b) { return {a[0] + b[0], a[1] + b[1], a[2] + b[2]}; }
Vec operator-(Vec a, Vec b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
Vec operator*(Vec a, float s) { return {a[0] * s, a[1] * s, a[2] * s}; }
Vec mul(Vec a, Vec b) { return {a[0] * b[0], a[1] * b[1], a[2] * b[2]}; }
float dot(Vec a, Vec b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec cross(Vec a, Vec b) { return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]}; }
Vec norm(Vec a) { return a * (1.0f / std::sqrt(dot(a, a))); }

struct Tri {
    Vec v0, v1, v2;
    uint32_t material;
};

// The payload row: packed, in the order of the columns declared below, then 8 opaque bytes.
#pragma pack(push, 1)
struct Row {
    float throughput[3];     // RL_F32 x 3
    uint32_t material;       // RL_U32
    uint8_t bounce;          // RL_U8
    double pdf;              // RL_F64
    uint32_t nodes_visited;  // RL_U32: the traversal counts `rtvtk analyze bvh` reads
    uint32_t box_tests;      // RL_U32
    uint32_t tri_tests;      // RL_U32
    uint64_t rng_state;      // 8 opaque bytes
};
#pragma pack(pop)

const uint32_t kMaterials = 4;  // white, red, green, light
const float kColors[kMaterials][3] = {{0.7f, 0.7f, 0.7f}, {0.7f, 0.1f, 0.1f}, {0.1f, 0.6f, 0.1f}, {0.8f, 0.8f, 0.8f}};
const float kEmission[kMaterials][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}, {12, 11, 9}};
const char *kNames[kMaterials] = {"white", "red", "green", "light"};
const Vec kPointLight = {0.75f, 0.8f, 0.3f};

std::vector<Tri> scene() {
    std::vector<Tri> t;
    auto quad = [&](Vec a, Vec b, Vec c, Vec d, uint32_t m) {
        t.push_back({a, b, c, m});
        t.push_back({a, c, d, m});
    };
    quad({0, 0, 0}, {1, 0, 0}, {1, 0, -1}, {0, 0, -1}, 0);      // floor
    quad({0, 1, 0}, {0, 1, -1}, {1, 1, -1}, {1, 1, 0}, 0);      // ceiling
    quad({0, 0, -1}, {1, 0, -1}, {1, 1, -1}, {0, 1, -1}, 0);    // back
    quad({0, 0, 0}, {0, 0, -1}, {0, 1, -1}, {0, 1, 0}, 1);      // left, red
    quad({1, 0, 0}, {1, 1, 0}, {1, 1, -1}, {1, 0, -1}, 2);      // right, green
    quad({0.4f, 0.999f, -0.4f}, {0.6f, 0.999f, -0.4f}, {0.6f, 0.999f, -0.6f}, {0.4f, 0.999f, -0.6f}, 3);  // light
    return t;
}

// A two-level BVH: the root over the box, one leaf per quad (its two triangles).
struct Node {
    Vec min, max;
    uint32_t first, count;  // leaf triangles (count 0: the root)
};

std::vector<Node> build_bvh(const std::vector<Tri> &tris) {
    std::vector<Node> nodes(1 + tris.size() / 2);
    auto grow = [](Node &n, Vec p) {
        for (int k = 0; k < 3; ++k) n.min[k] = std::fmin(n.min[k], p[k]), n.max[k] = std::fmax(n.max[k], p[k]);
    };
    for (Node &n : nodes) n = {{1e30f, 1e30f, 1e30f}, {-1e30f, -1e30f, -1e30f}, 0, 0};
    for (size_t q = 0; q < tris.size() / 2; ++q) {
        Node &leaf = nodes[1 + q];
        leaf.first = (uint32_t)(2 * q);
        leaf.count = 2;
        for (size_t i = 2 * q; i < 2 * q + 2; ++i)
            for (const Vec &v : {tris[i].v0, tris[i].v1, tris[i].v2}) grow(leaf, v), grow(nodes[0], v);
    }
    return nodes;
}

// The slab test: whether the ray enters the box (t >= 0).
bool enters(const Node &n, Vec o, Vec d) {
    float t0 = 0, t1 = 1e30f;
    for (int k = 0; k < 3; ++k) {
        float inv = 1.0f / d[k], a = (n.min[k] - 1e-4f - o[k]) * inv, b = (n.max[k] + 1e-4f - o[k]) * inv;
        t0 = std::fmax(t0, std::fmin(a, b));
        t1 = std::fmin(t1, std::fmax(a, b));
    }
    return t0 <= t1;
}

// Closest hit (Moller-Trumbore): t, triangle, or t < 0 for a miss.
float intersect(const std::vector<Tri> &tris, Vec o, Vec d, int64_t &prim) {
    float best = -1.0f;
    prim = RL_MISS;
    for (size_t i = 0; i < tris.size(); ++i) {
        Vec e1 = tris[i].v1 - tris[i].v0, e2 = tris[i].v2 - tris[i].v0, p = cross(d, e2);
        float det = dot(e1, p);
        if (std::fabs(det) < 1e-12f) continue;
        float inv = 1.0f / det;
        Vec s = o - tris[i].v0;
        float u = dot(s, p) * inv;
        if (u < 0 || u > 1) continue;
        Vec q = cross(s, e1);
        float v = dot(d, q) * inv;
        if (v < 0 || u + v > 1) continue;
        float t = dot(e2, q) * inv;
        if (t > 1e-5f && (best < 0 || t < best)) {
            best = t;
            prim = (int64_t)i;
        }
    }
    return best;
}

void die(const char *what) {
    std::fprintf(stderr, "%s: %s\n", what, rlLastError());
    std::exit(1);
}

}  // namespace

int main(int argc, char **argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: cpp_tracer OUT [--bug]\n");
        return 2;
    }
    const bool bug = argc > 2 && std::strcmp(argv[2], "--bug") == 0;
    const rl_column columns[] = {{"throughput", RL_F32, 3}, {"material", RL_U32, 1}, {"bounce", RL_U8, 1},
                                 {"pdf", RL_F64, 1},        {"nodes_visited", RL_U32, 1}, {"box_tests", RL_U32, 1},
                                 {"tri_tests", RL_U32, 1}};
    const size_t kColumns = sizeof columns / sizeof columns[0];
    // Refusals name what is wrong (and record nothing).
    const rl_column bad[] = {{"x", 42, 1}};
    if (rlInitColumns(argv[1], bad, 1, 0, 0) != nullptr || std::strstr(rlLastError(), "type 42") == nullptr) die("expected a type error");
    // Every ray's call site is recorded (RL_ADD_RAY names it): SQL groups rays by source line.
    rl_recorder *rec = rlInitColumns(argv[1], columns, kColumns, 8, RL_RECORD_SITES);
    if (!rec) die("rlInitColumns");
    if (rlPayloadRowSize(rec) != (int64_t)sizeof(Row)) die("row size");

    const std::vector<Tri> tris = scene();
    std::vector<float> verts;
    std::vector<uint32_t> mats;
    for (const Tri &t : tris) {
        for (const Vec &v : {t.v0, t.v1, t.v2}) verts.insert(verts.end(), v.begin(), v.end());
        mats.push_back(t.material);
    }
    if (rlSetTriangles(rec, tris.size(), verts.data(), mats.data(), kMaterials, &kColors[0][0], &kEmission[0][0], kNames) != 0)
        die("rlSetTriangles");
    // The BVH, and below every ray's visits to it.
    const std::vector<Node> bvh = build_bvh(tris);
    {
        std::vector<rl_bvh_node> nodes;
        std::vector<uint32_t> prims(tris.size());
        for (size_t i = 0; i < prims.size(); ++i) prims[i] = (uint32_t)i;
        for (size_t i = 0; i < bvh.size(); ++i)
            nodes.push_back({i == 0 ? -1 : 0, {bvh[i].min[0], bvh[i].min[1], bvh[i].min[2]},
                             {bvh[i].max[0], bvh[i].max[1], bvh[i].max[2]}, bvh[i].first, bvh[i].count});
        if (rlSetBvh(rec, nodes.size(), nodes.data(), prims.size(), prims.data()) != 0) die("rlSetBvh");
    }
    struct Traversal {
        std::vector<uint32_t> ids;
        std::vector<int8_t> hit;
        uint32_t boxes, tests;
    };
    auto traverse = [&](Vec o, Vec d) {
        Traversal tr{{0}, {-1}, 1, 0};
        for (uint32_t i = 1; i < bvh.size(); ++i) {
            ++tr.boxes;
            if (!enters(bvh[i], o, d)) continue;
            std::vector<Tri> leaf(tris.begin() + bvh[i].first, tris.begin() + bvh[i].first + bvh[i].count);
            int64_t p;
            tr.ids.push_back(i);
            tr.hit.push_back(intersect(leaf, o, d, p) > 0 ? 1 : 0);
            tr.tests += bvh[i].count;
        }
        return tr;
    };
    auto visits = [&](const Traversal &tr) {
        if (rlAddRayVisits(rec, tr.ids.size(), tr.ids.data(), tr.hit.data()) != 0) die("rlAddRayVisits");
    };
    const float point_intensity[3] = {0.4f, 0.4f, 0.5f};
    if (rlSetPointLights(rec, 1, kPointLight.data(), point_intensity) != 0) die("rlSetPointLights");
    const float nan_light[3] = {NAN, 0, 0};
    if (rlSetPointLights(rec, 1, nan_light, point_intensity) == 0) die("expected a point light error");
    if (rlSetPointLights(rec, 1, kPointLight.data(), point_intensity) != 0) die("rlSetPointLights");

    // The camera: at (0.5, 0.5, 1.6) looking down -z, OpenGL style; 40 degrees across x.
    const int W = 24, H = 18, SPP = 2, THREADS = 3;
    const float cam_to_world[16] = {1, 0, 0, 0.5f, 0, 1, 0, 0.5f, 0, 0, 1, 1.6f, 0, 0, 0, 1};
    if (rlSetCameraMatrix(rec, cam_to_world, -1.0f, 40.0f, RL_FOV_X, W, H) != 0) die("rlSetCameraMatrix");
    const float tan_x = std::tan(40.0f * 3.14159265f / 360.0f), tan_y = tan_x * H / W;

    std::atomic<uint64_t> counts[3] = {};  // camera, shadow, diffuse
    auto work = [&](int first_row) {
        std::mt19937_64 rng(1234 + first_row);
        std::uniform_real_distribution<float> uni(0.0f, 1.0f);
        for (int y = first_row; y < H; y += THREADS) {
            for (int x = 0; x < W; ++x) {
                for (int s = 0; s < SPP; ++s) {
                    if (rlBeginTree(rec, x, y, s) != 0) die("rlBeginTree");
                    Vec o = {0.5f, 0.5f, 1.6f};
                    float sx = (2 * (x + uni(rng)) / W - 1) * tan_x, sy = (1 - 2 * (y + uni(rng)) / H) * tan_y;
                    Vec d = norm(Vec{sx, sy, -1});
                    Vec throughput = {1, 1, 1};
                    int descended = 0;
                    for (uint8_t bounce = 0; bounce < 3; ++bounce) {
                        int64_t prim;
                        float t = intersect(tris, o, d, prim);
                        Traversal tr = traverse(o, d);
                        Row row{{throughput[0], throughput[1], throughput[2]}, prim >= 0 ? tris[prim].material : 0u, bounce, 1.0,
                                (uint32_t)tr.ids.size(), tr.boxes, tr.tests, rng()};
                        if (RL_ADD_RAY(rec, o.data(), d.data(), t, bounce == 0 ? RL_CAMERA : RL_DIFFUSE, prim, &row, sizeof row) != 0)
                            die("rlAddRay");
                        visits(tr);
                        counts[bounce == 0 ? 0 : 2]++;
                        if (prim < 0 || tris[prim].material == 3) break;
                        Vec p = o + d * t;
                        Vec n = norm(cross(tris[prim].v1 - tris[prim].v0, tris[prim].v2 - tris[prim].v0));
                        if (dot(n, d) > 0) n = n * -1.0f;
                        Vec so = p + n * 1e-4f;
                        rlDescendTree(rec);
                        ++descended;
                        // Two shadow rays: to a random point of the area light, and to the point light.
                        Vec lp = {0.4f + 0.2f * uni(rng), 0.999f, -0.4f - 0.2f * uni(rng)};
                        Vec targets[2] = {lp, kPointLight};
                        if (bug && n[1] > 0.9f) targets[1][1] = 2 * p[1] - kPointLight[1];
                        for (int l = 0; l < 2; ++l) {
                            Vec sd = norm(targets[l] - so);
                            int64_t sp;
                            float st = intersect(tris, so, sd, sp);
                            Traversal str = traverse(so, sd);
                            Row srow{{throughput[0], throughput[1], throughput[2]}, sp >= 0 ? tris[sp].material : 0u, bounce, 1.0,
                                     (uint32_t)str.ids.size(), str.boxes, str.tests, rng()};
                            int added = l == 0 ? RL_ADD_RAY(rec, so.data(), sd.data(), st, RL_SHADOW, sp, &srow, sizeof srow)   // area light
                                               : RL_ADD_RAY(rec, so.data(), sd.data(), st, RL_SHADOW, sp, &srow, sizeof srow);  // point light
                            if (added != 0) die("rlAddRay");
                            counts[1]++;
                        }
                        // A wrong payload size is refused, naming the row's size.
                        if (rlAddRay(rec, so.data(), d.data(), 1.0f, RL_SHADOW, RL_MISS, &row, 3) == 0) die("expected a size error");
                        // Cosine-weighted bounce.
                        float u1 = uni(rng), u2 = uni(rng), r = std::sqrt(u1), phi = 6.2831853f * u2;
                        Vec tx = norm(cross(n, std::fabs(n[0]) > 0.9f ? Vec{0, 1, 0} : Vec{1, 0, 0})), ty = cross(n, tx);
                        d = norm(tx * (r * std::cos(phi)) + ty * (r * std::sin(phi)) + n * std::sqrt(1 - u1));
                        o = so;
                        throughput = mul(throughput, Vec{kColors[tris[prim].material][0], kColors[tris[prim].material][1],
                                                         kColors[tris[prim].material][2]});
                    }
                    // Back to the root before the tree ends (rl reports a tree left below it).
                    for (; descended > 0; --descended) rlAscendTree(rec);
                    if (rlEndTree(rec) < 0) die("rlEndTree");
                }
            }
        }
    };
    std::vector<std::thread> threads;
    for (int i = 0; i < THREADS; ++i) threads.emplace_back(work, i);
    for (std::thread &t : threads) t.join();
    if (rlFinish(rec) != 0) die("rlFinish");

    // Read mode: the trees come back.
    rl_reader *reader = rlOpen(argv[1]);
    if (!reader) die("rlOpen");
    if (rlTreeCount(reader) != (uint64_t)(W * H * SPP)) die("tree count");
    rl_tree tree;
    rl_ray ray;
    uint64_t rays = 0;
    while (rlReadTree(reader, &tree) == 1) {
        while (rlReadRay(reader, &ray, nullptr, 0) == 1) ++rays;
        if (rlNextTree(reader) != 1) break;
    }
    rlClose(reader);
    if (rays != counts[0] + counts[1] + counts[2]) die("ray count read back");

    // Immediate mode: a recording in memory, read while it records (as a viewer of a live
    // renderer would).
    rl_recorder *live = rlInitImmediate(columns, kColumns, 8, 0, 0);
    if (!live) die("rlInitImmediate");
    rl_reader *cursor = rlOpenRecording(live);
    if (!cursor) die("rlOpenRecording");
    for (int round = 1; round <= 2; ++round) {
        for (int x = 0; x < 4; ++x) {
            rlBeginTree(live, x, round, 0);
            Vec o = {0.5f, 0.5f, 1.6f}, d = {0, 0, -1};
            int64_t prim;
            float t = intersect(tris, o, d, prim);
            Row row{{1, 1, 1}, prim >= 0 ? tris[prim].material : 0u, 0, 1.0, 0, 0, 0, 0};
            if (rlAddRay(live, o.data(), d.data(), t, RL_CAMERA, prim, &row, sizeof row) != 0) die("rlAddRay (immediate)");
            if (rlEndTree(live) < 0) die("rlEndTree (immediate)");
        }
        if (rlTreeCount(cursor) != (uint64_t)(4 * round)) die("trees seen while recording");
    }
    if (rlReadTree(cursor, &tree) != 1 || tree.ray_count != 1) die("a tree read while recording");
    rlClose(cursor);
    if (rlFinish(live) != 0) die("rlFinish (immediate)");
    // rlOpenRecording refuses a write-mode recorder.
    rl_recorder *disk = rlInit((std::string(argv[1]) + "-x").c_str(), 0);
    if (rlOpenRecording(disk) != nullptr || std::strstr(rlLastError(), "immediate") == nullptr) die("expected a mode error");
    rlFinish(disk);

    std::printf("camera %llu shadow %llu diffuse %llu\n", (unsigned long long)counts[0], (unsigned long long)counts[1],
                (unsigned long long)counts[2]);
    return 0;
}
