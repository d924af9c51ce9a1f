// Embree 3's own builders on a top level like the one `cargo bench --bench bvh --
// tlas_build` builds: N instances (365,041 by default) scattered over 300 m x 300 m,
// scaled 0.6-1.6 and turned about the vertical, on 2 threads. It times
//   - a scene of N instance geometries committed (what an Embree application does), and
//   - rtcBuildBVH over the same number of boxes, 8-wide, one primitive per leaf, at
//     RTC_BUILD_QUALITY_MEDIUM (binned SAH) and RTC_BUILD_QUALITY_LOW (Morton).
//
// build: g++ -O3 -march=native -std=c++17 tlas_build.cpp -lembree3 -lpthread -o tlas_build
// run:   ./tlas_build [N] [repeats]
#include <embree3/rtcore.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <new>
#include <random>
#include <vector>

static double now() {
    return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

struct Node { virtual ~Node() {} };
struct Inner : Node { RTCBounds bounds[8]; Node* children[8]; unsigned count; };
struct Leaf : Node { unsigned id; };

static void* create_node(RTCThreadLocalAllocator a, unsigned count, void*) {
    Inner* node = new (rtcThreadLocalAlloc(a, sizeof(Inner), 16)) Inner;
    node->count = count;
    return node;
}
static void set_children(void* node, void** children, unsigned count, void*) {
    for (unsigned i = 0; i < count; i++) static_cast<Inner*>(node)->children[i] = static_cast<Node*>(children[i]);
}
static void set_bounds(void* node, const RTCBounds** bounds, unsigned count, void*) {
    for (unsigned i = 0; i < count; i++) static_cast<Inner*>(node)->bounds[i] = *bounds[i];
}
static void* create_leaf(RTCThreadLocalAllocator a, const RTCBuildPrimitive* prims, size_t, void*) {
    Leaf* leaf = new (rtcThreadLocalAlloc(a, sizeof(Leaf), 16)) Leaf;
    leaf->id = prims[0].primID;
    return leaf;
}

int main(int argc, char** argv) {
    const int n = argc > 1 ? atoi(argv[1]) : 365041;
    const int repeats = argc > 2 ? atoi(argv[2]) : 5;
    RTCDevice device = rtcNewDevice("threads=2");

    // Six small species (a 12-triangle box each), instanced with random transforms.
    float vertices[8 * 3];
    for (int i = 0; i < 8; i++) {
        vertices[i * 3] = (i & 1) ? 1.f : -1.f;
        vertices[i * 3 + 1] = (i & 2) ? 4.f : 0.f;
        vertices[i * 3 + 2] = (i & 4) ? 1.f : -1.f;
    }
    unsigned indices[36] = {0, 1, 3, 0, 3, 2, 4, 5, 7, 4, 7, 6, 0, 1, 5, 0, 5, 4,
                            2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 3, 7, 1, 7, 5};
    std::vector<RTCScene> species;
    for (int s = 0; s < 6; s++) {
        RTCScene scene = rtcNewScene(device);
        RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
        rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, vertices, 0, 12, 8);
        rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, indices, 0, 12, 12);
        rtcCommitGeometry(g);
        rtcAttachGeometry(scene, g);
        rtcReleaseGeometry(g);
        rtcCommitScene(scene);
        species.push_back(scene);
    }
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> uniform(0.f, 1.f);
    std::vector<float> transforms(size_t(n) * 12);
    std::vector<RTCBuildPrimitive> boxes(n);
    for (int i = 0; i < n; i++) {
        float scale = 0.6f + uniform(rng), angle = 6.3f * uniform(rng);
        float c = std::cos(angle) * scale, s = std::sin(angle) * scale;
        float x = -150.f + 300.f * uniform(rng), y = 5.f * uniform(rng), z = -150.f + 300.f * uniform(rng);
        float* t = &transforms[size_t(i) * 12];
        float row_major[12] = {c, 0, s, x, 0, scale, 0, y, -s, 0, c, z};
        for (int k = 0; k < 12; k++) t[k] = row_major[k];
        float r = 1.4142f * scale;
        boxes[i] = {x - r, y, z - r, 0, x + r, y + 4.f * scale, z + r, unsigned(i)};
    }

    for (int rep = 0; rep < repeats; rep++) {
        RTCScene top = rtcNewScene(device);
        rtcSetSceneBuildQuality(top, RTC_BUILD_QUALITY_MEDIUM);
        double t0 = now();
        for (int i = 0; i < n; i++) {
            RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
            rtcSetGeometryInstancedScene(g, species[i % 6]);
            rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, &transforms[size_t(i) * 12]);
            rtcCommitGeometry(g);
            rtcAttachGeometry(top, g);
            rtcReleaseGeometry(g);
        }
        double t1 = now();
        rtcCommitScene(top);
        double t2 = now();
        rtcReleaseScene(top);

        double build_ms[2];
        for (int quality = 0; quality < 2; quality++) {
            std::vector<RTCBuildPrimitive> prims(size_t(n) * 2);
            std::copy(boxes.begin(), boxes.end(), prims.begin());
            RTCBVH bvh = rtcNewBVH(device);
            RTCBuildArguments args = rtcDefaultBuildArguments();
            args.byteSize = sizeof(args);
            args.buildQuality = quality == 0 ? RTC_BUILD_QUALITY_MEDIUM : RTC_BUILD_QUALITY_LOW;
            args.maxBranchingFactor = 8;
            args.maxDepth = 1024;
            args.sahBlockSize = 1;
            args.minLeafSize = 1;
            args.maxLeafSize = 1;
            args.traversalCost = 1.f;
            args.intersectionCost = 1.f;
            args.bvh = bvh;
            args.primitives = prims.data();
            args.primitiveCount = n;
            args.primitiveArrayCapacity = prims.size();
            args.createNode = create_node;
            args.setNodeChildren = set_children;
            args.setNodeBounds = set_bounds;
            args.createLeaf = create_leaf;
            double b0 = now();
            rtcBuildBVH(&args);
            build_ms[quality] = (now() - b0) * 1e3;
            rtcReleaseBVH(bvh);
        }
        printf("n=%d  instance scene: attach %.1f ms, commit %.1f ms   rtcBuildBVH: medium (SAH) %.1f ms, low (Morton) %.1f ms\n",
               n, (t1 - t0) * 1e3, (t2 - t1) * 1e3, build_ms[0], build_ms[1]);
    }
    for (RTCScene s : species) rtcReleaseScene(s);
    rtcReleaseDevice(device);
}
