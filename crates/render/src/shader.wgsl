// Depth + instance rendering. One uniform entry per (view, object), selected by dynamic offset.
struct Entry {
    // model -> camera (OpenCV frame), column-major
    model_view: mat4x4<f32>,
    // (2 fx / W, 2 (cx + 0.5) / W, 2 fy / H, 2 (cy + 0.5) / H)
    proj: vec4<f32>,
    // (near, unused, unused, unused)
    clip: vec4<f32>,
    // (instance id, unused, unused, unused)
    id: vec4<u32>,
};

@group(0) @binding(0) var<uniform> entry: Entry;

struct VsOut {
    @builtin(position) position: vec4<f32>,
    @location(0) cam: vec3<f32>,
};

@vertex
fn vs_main(@location(0) pos: vec3<f32>) -> VsOut {
    let p = (entry.model_view * vec4<f32>(pos, 1.0)).xyz;
    var out: VsOut;
    // Framebuffer x = fx x/z + cx + 0.5 (pixel centres at i + 0.5), NDC y points up.
    // Reversed, infinite far plane: z_ndc = near / z.
    out.position = vec4<f32>(
        entry.proj.x * p.x + (entry.proj.y - 1.0) * p.z,
        p.z - entry.proj.z * p.y - entry.proj.w * p.z,
        entry.clip.x,
        p.z,
    );
    out.cam = p;
    return out;
}

@fragment
fn fs_main(in: VsOut) -> @location(0) vec2<u32> {
    // Perspective-correct interpolation of the camera-frame position gives the exact z of the
    // triangle's plane along this pixel's ray.
    let z = in.cam.z;
    let n = cross(dpdx(in.cam), dpdy(in.cam));
    let len = length(n);
    var c = 1.0;
    if (len > 0.0) {
        c = clamp(abs(dot(n / len, normalize(in.cam))), 0.0, 1.0);
    }
    let q = u32(round(c * 65535.0));
    return vec2<u32>(bitcast<u32>(z), (entry.id.x & 0xffffu) | (q << 16u));
}
