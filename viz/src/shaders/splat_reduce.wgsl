// The largest ray count of a density accumulation and the pixels any ray reached (`splat.rs`):
// a workgroup's maximum first, then one atomic per workgroup; and a histogram of the covered
// pixels' counts (stats[2 + n] for n < HIST - 1, the last bucket for more), from which the alpha
// style picks its opacity without reading the accumulation back.

@group(0) @binding(0) var<storage, read> acc: array<u32>;
@group(0) @binding(1) var<storage, read_write> stats: array<atomic<u32>>;
@group(0) @binding(2) var<uniform> splat: Splat;

const HIST: u32 = 4096u;

var<workgroup> wmax: atomic<u32>;
var<workgroup> wcov: atomic<u32>;

@compute @workgroup_size(256)
fn reduce(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    if li == 0u {
        atomicStore(&wmax, 0u);
        atomicStore(&wcov, 0u);
    }
    workgroupBarrier();
    let k = gid.x + gid.y * groups.x * 256u;
    if k < splat.size.z {
        let n = acc[k * 5u];
        if n > 0u {
            atomicMax(&wmax, n);
            atomicAdd(&wcov, 1u);
            atomicAdd(&stats[2u + min(n, HIST - 1u)], 1u);
        }
    }
    workgroupBarrier();
    if li == 0u {
        atomicMax(&stats[0], atomicLoad(&wmax));
        atomicAdd(&stats[1], atomicLoad(&wcov));
    }
}
