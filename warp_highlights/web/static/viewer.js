// warp-highlights web viewer: relights an exported field as Relighter does (warp_highlights/web/PORTING.md).
// The light is located and the Gaussians are moved on the CPU (float64); fragment shaders draw them and
// add the residual: each captured light's residual decoded once into a float16 texture layer and
// blended from the three corner lights (low-rank and uncompressed fields), or the learned residual's
// decoder run per pixel at the located direction (a decoder that sees the highlights takes the Gaussians'
// luminance at the pixel as inputs and gives the whole image: the Gaussians are not added to it).
// This file holds one thing: the page's relighting, as Relighter does it.

const TYPES = { "<f8": Float64Array, "<f4": Float32Array, "<f2": Uint16Array, "<i4": Int32Array, "|u1": Uint8Array, "<u2": Uint16Array };
export const FORMAT_VERSION = 3;
const SEEING_FORMAT_VERSION = 4; // version 3's layout, a learned decoder that sees the highlights
const DECODED_BYTES = 512 * 1024 * 1024; // largest decoded residual stack (as Relighter's DECODED_RESIDUAL_BYTES)
const FLOAT16_SAFE = "6.0e4";

async function fetchArrays(base, manifest) {
  const arrays = {};
  await Promise.all(Object.entries(manifest.arrays).map(async ([name, spec]) => {
    const response = await fetch(new URL(spec.file, base));
    if (!response.ok) throw new Error(`${spec.file}: ${response.status} ${response.statusText}`);
    arrays[name] = typed(spec, await inflated(spec, await response.arrayBuffer()));
  }));
  return arrays;
}

async function inflated(spec, bytes) {
  // an array's bytes: gzip inflated by the browser, or as they are (also where a server sent the .gz
  // with Content-Encoding: gzip, so that the browser has inflated it already: no gzip magic number)
  const head = new Uint8Array(bytes, 0, Math.min(2, bytes.byteLength));
  if (spec.encoding !== "gzip" || head[0] !== 0x1f || head[1] !== 0x8b) return bytes;
  if (typeof DecompressionStream === "undefined") throw new Error("this browser cannot inflate gzip (no DecompressionStream): use a current browser");
  return new Response(new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"))).arrayBuffer();
}

function typed(spec, buffer) {
  const Type = TYPES[spec.dtype];
  if (!Type) throw new Error(`${spec.file}: unsupported dtype ${spec.dtype}`);
  const expected = spec.shape.reduce((a, b) => a * b, 1) * Type.BYTES_PER_ELEMENT;
  if (buffer.byteLength !== expected) throw new Error(`${spec.file}: ${buffer.byteLength} bytes, the manifest says ${expected}`);
  return new Type(buffer);
}

async function fromBase64(text) {
  // the browser's own decoder through a data: URL (native, fast), else atob byte by byte
  try {
    return await (await fetch(`data:application/octet-stream;base64,${text}`)).arrayBuffer();
  } catch {
    const binary = atob(text), bytes = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
    return bytes.buffer;
  }
}

function checkManifest(manifest) {
  const seeing = Boolean(manifest.residual && manifest.residual.sees_highlights);
  if (manifest.format !== "warp-highlights web viewer" || manifest.version !== (seeing ? SEEING_FORMAT_VERSION : FORMAT_VERSION)) {
    throw new Error(`manifest.json is not a warp-highlights viewer of version ${FORMAT_VERSION} or ${SEEING_FORMAT_VERSION}: export the field again with this version`);
  }
  return manifest;
}

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];

export function locate(m, a, direction) {
  // face, barycentric weights (clamped onto a dome's rim where outside): PORTING.md section 2
  let q = direction.slice();
  const big = Math.max(Math.abs(q[0]), Math.abs(q[1]), Math.abs(q[2]));
  q = q.map((v) => v / big);
  const length = Math.hypot(q[0], q[1], q[2]);
  q = q.map((v) => v / length);
  let best = 0, bestDepth = -Infinity;
  for (let f = 0; f < m.faces; f++) {
    let depth = Infinity;
    for (let j = 0; j < 3; j++) {
      const o = (f * 3 + j) * 3;
      depth = Math.min(depth, q[0] * a.edge_normals[o] + q[1] * a.edge_normals[o + 1] + q[2] * a.edge_normals[o + 2]);
    }
    if (depth > bestDepth) { bestDepth = depth; best = f; }
  }
  let point = q, opposite = -1, clamped = false;
  if (m.is_dome && bestDepth < -1e-12) {
    clamped = true;
    const rims = a.rim_face.length;
    const vec = (e, k) => [a.rims[(e * 5 + k) * 3], a.rims[(e * 5 + k) * 3 + 1], a.rims[(e * 5 + k) * 3 + 2]];
    let closest = -3, chosen = 0, chosenOver = false, chosenOff = 0;
    for (let e = 0; e < rims; e++) {
      const off = dot(q, vec(e, 2));
      const foot = Math.sqrt(Math.max(1 - off * off, 0));
      const over = dot(q, vec(e, 3)) >= 0 && dot(q, vec(e, 4)) >= 0 && foot > 1e-12;
      const close = over ? foot : Math.max(dot(q, vec(e, 0)), dot(q, vec(e, 1)));
      if (close > closest) { closest = close; chosen = e; chosenOver = over; chosenOff = off; }
    }
    if (chosenOver) {
      const n = vec(chosen, 2);
      const p = [q[0] - chosenOff * n[0], q[1] - chosenOff * n[1], q[2] - chosenOff * n[2]];
      const l = Math.hypot(p[0], p[1], p[2]);
      point = p.map((v) => v / l);
    } else {
      point = dot(q, vec(chosen, 0)) >= dot(q, vec(chosen, 1)) ? vec(chosen, 0) : vec(chosen, 1);
    }
    best = a.rim_face[chosen];
    opposite = a.rim_opposite[chosen];
  }
  const w = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    const o = best * 9 + k * 3;
    w[k] = a.inverses[o] * point[0] + a.inverses[o + 1] * point[1] + a.inverses[o + 2] * point[2];
    if (k === opposite || w[k] < 0) w[k] = 0;
  }
  const total = w[0] + w[1] + w[2];
  return { face: best, weights: w.map((v) => Math.fround(v / total)), located: point, clamped };
}

function arc(mA, mB, delta, t, straightBelow) {
  const chord = [mB[0] - mA[0], mB[1] - mA[1]];
  const sh = Math.sin(delta / 2);
  if (Math.abs(delta) < straightBelow || sh === 0) return [mA[0] + t * chord[0], mA[1] + t * chord[1]];
  const k = Math.sin(t * delta / 2) / sh, phi = (t - 1) * delta / 2;
  const c = Math.cos(phi), s = Math.sin(phi);
  return [mA[0] + k * (c * chord[0] - s * chord[1]), mA[1] + k * (s * chord[0] + c * chord[1])];
}

export function rbfWeights(m, a, located) {
  // every light's radial basis weight phi(w)^T (K + lambda I)^-1 at the located direction w: PORTING.md section 5.2
  const n = m.lights, s2 = m.residual.rbf_sigma * m.residual.rbf_sigma, phi = new Float64Array(n), out = new Float64Array(n);
  for (let j = 0; j < n; j++) {
    const dx = located[0] - a.directions[3 * j], dy = located[1] - a.directions[3 * j + 1], dz = located[2] - a.directions[3 * j + 2];
    phi[j] = Math.exp(-(dx * dx + dy * dy + dz * dz) / s2);
  }
  for (let j = 0; j < n; j++) {
    if (phi[j] === 0) continue;
    for (let i = 0; i < n; i++) out[i] += phi[j] * a.rbf_inverse[j * n + i];
  }
  return out;
}

export function movedGaussians(m, a, location, method) {
  // the Gaussians of the query, 8 floats each: mu.x, mu.y, peak, cos, sin, 1/(sx^2+eps), 1/(sy^2+eps), reach^2;
  // "alpha" keeps every corner's own Gaussians in place (the blend of the captured lights' images)
  const N = m.capacity, out = [];
  const tau = Math.exp(-m.cutoff * m.cutoff / 2);
  const f = location.face, w = location.weights;
  const g = (table, row, p) => { const o = (row * N + p) * 6; return table.subarray(o, o + 6); };
  for (let k = 0; k < 3; k++) {
    const A = a.faces[f * 3 + k], lA = w[k], lB = w[(k + 1) % 3], lC = w[(k + 2) % 3];
    const eB = a.face_edges[(f * 3 + k) * 2], eC = a.face_edges[(f * 3 + k) * 2 + 1];
    for (let p = 0; p < N; p++) {
      if (!a.estimated_active[A * N + p] || lA <= 0) continue;
      const G = g(a.estimated, A, p);
      let amp, mu, sx, sy, theta;
      if (!a.moving[A * N + p] || method === "alpha") {
        [amp, mu, sx, sy, theta] = [G[0], [G[1], G[2]], G[3], G[4], G[5]];
      } else {
        const Gb = g(a.retargeted, eB, p), Gc = g(a.retargeted, eC, p);
        const dB = a.path_delta[eB * N + p], dC = a.path_delta[eC * N + p];
        if (method === "circular") {
          const b = arc([G[1], G[2]], [Gb[1], Gb[2]], dB, lB, m.straight_below);
          const c = arc([G[1], G[2]], [Gc[1], Gc[2]], dC, lC, m.straight_below);
          mu = [b[0] + c[0] - G[1], b[1] + c[1] - G[2]];
        } else {
          mu = [lA * G[1] + lB * Gb[1] + lC * Gc[1], lA * G[2] + lB * Gb[2] + lC * Gc[2]];
        }
        amp = lA * G[0] + lB * Gb[0] + lC * Gc[0];
        sx = lA * G[3] + lB * Gb[3] + lC * Gc[3];
        sy = lA * G[4] + lB * Gb[4] + lC * Gc[4];
        theta = G[5] + lB * dB + lC * dC;
      }
      const peak = lA * amp * amp / (1 - tau);
      if (![peak, mu[0], mu[1], sx, sy, theta].every(Number.isFinite)) continue;
      // beyond cutoff * the larger sigma a pixel gets nothing
      const vx = sx * sx + m.sigma_eps, vy = sy * sy + m.sigma_eps;
      out.push(mu[0], mu[1], peak, Math.cos(theta), Math.sin(theta), 1 / vx, 1 / vy, m.cutoff * m.cutoff * Math.max(vx, vy));
    }
  }
  return new Float32Array(out);
}

// --- shaders ------------------------------------------------------------------------------------

const VERTEX = `#version 300 es
in vec2 corner; void main() { gl_Position = vec4(corner, 0.0, 1.0); }`;

const HEADER = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp sampler2DArray;
precision highp usampler2D; precision highp usampler2DArray;`;

function pixelOf(m) { return `ivec2 pixel = ivec2(int(gl_FragCoord.x), ${m.height} - 1 - int(gl_FragCoord.y));`; }

function stackSource(m) {
  // R(x) of a low-rank residual for the blended coefficients in the factors texture (PORTING.md 5.2)
  const r = m.residual, Y = r.luminance, C = m.channels === 3 ? r.chroma : undefined;
  const scale = m.arrays.scale ? "texelFetch(scaleMap, pixel, 0).r" : "1.0";
  return `
uniform highp usampler2DArray luminanceCodes; uniform sampler2D luminanceMean; uniform sampler2D factors;
uniform float luminanceWeight; uniform float luminanceConstant;
${C ? "uniform highp usampler2DArray chromaCodes; uniform sampler2D chromaMean; uniform float chromaWeight; uniform float chromaConstant;" : ""}
${m.arrays.scale ? "uniform sampler2D scaleMap;" : ""}
vec3 residual(ivec2 pixel) {
  float s = ${scale};
  float Y = luminanceWeight * texelFetch(luminanceMean, pixel, 0).r + luminanceConstant;
  for (int g = 0; g < ${Y.groups}; g++) Y += dot(texelFetch(factors, ivec2(g, 0), 0), vec4(texelFetch(luminanceCodes, ivec3(pixel, g), 0)));
  Y *= s;
${C ? `  vec2 C = chromaWeight * texelFetch(chromaMean, pixel, 0).rg + vec2(chromaConstant);
  for (int g = 0; g < ${C.groups}; g++) {
    vec4 code = vec4(texelFetch(chromaCodes, ivec3(pixel, g), 0));
    C += vec2(dot(texelFetch(factors, ivec2(${Y.groups} + g, 0), 0), code), dot(texelFetch(factors, ivec2(${Y.groups + C.groups} + g, 0), 0), code));
  }
  C *= s;
  return vec3(Y + C.y, Y - (0.2126 * C.y + 0.0722 * C.x) / 0.7152, Y + C.x);` : "  return vec3(Y);"}
}`;
}

function layersSource(m) {
  // R~(x) = the corners' decoded (or stored) residual images, blended
  const take = m.channels === 3 ? ".rgb" : ".rrr";
  return `
uniform sampler2DArray residualImages; uniform ivec3 corners; uniform vec3 weights;
vec3 residual(ivec2 pixel) {
  return weights.x * texelFetch(residualImages, ivec3(pixel, corners.x), 0)${take} + weights.y * texelFetch(residualImages, ivec3(pixel, corners.y), 0)${take}
       + weights.z * texelFetch(residualImages, ivec3(pixel, corners.z), 0)${take};
}`;
}

function decoderLayout(m) {
  // the learned residual's decoder in vec4s: hidden widths (multiples of 4), w0's columns (12, or 14 where it sees
  // the highlights), and the Decoder block's offsets (in vec4s) of w0 (a row of 3 vec4s per unit: the 9 code inputs,
  // then the direction's three, which the first bias takes in per frame), each hidden bias, the output layer's rows
  // and bias, the unit, and where it sees the highlights the weights of sqrt(g) and of g (two vec4s per four units)
  const hidden = (m.residual && m.residual.hidden) || [48, 48, 48];
  const seeing = Boolean(m.residual && m.residual.sees_highlights);
  const groups = hidden.map((w) => w / 4);
  const biases = [];
  let at = 3 * hidden[0];
  for (const g of groups) { biases.push(at); at += g; }
  const out = at, outBias = out + 3 * groups[groups.length - 1], unit = outBias + 1, highlights = unit + 1;
  const vec4s = highlights + (seeing ? 2 * groups[0] : 0);
  return { hidden, groups, biases, out, outBias, unit, seeing, columns: seeing ? 14 : 12, highlights, vec4s };
}

function learnedSource(m) {
  // R(x, d) = unit * decode_display(MLP(z(x), d)), the direction folded into the first bias (PORTING.md 1.5c); a
  // decoder that sees the highlights also takes sqrt(g) and g, g = max(S, 0) / unit of the pixel's S (field units)
  const L = decoderLayout(m), G = L.groups, last = G.length - 1;
  const layer = (k, input, inGroups) => {
    const weights = k === 0 ? "decoder" : `w${k}`, bias = `decoder[${L.biases[k]} + r]`;
    const dots = (row) => Array.from({ length: inGroups }, (_, q) => `dot(${weights}[${row} * ${inGroups} + ${q}], ${input}[${q}])`).join(" + ");
    const seen = k === 0 && L.seeing ? ` + decoder[${L.highlights} + 2 * r] * root + decoder[${L.highlights} + 2 * r + 1] * g` : "";
    return `  for (int r = 0; r < ${G[k]}; r++) {
    vec4 v = vec4(${[0, 1, 2, 3].map((t) => dots(`(4 * r + ${t})`)).join(",\n                  ")}) + ${bias}${seen};
    h${k}[r] = max(v, 0.0) + exp(min(v, 0.0)) - 1.0;
  }`;
  };
  const hiddenBlocks = G.slice(1).map((g, i) => `layout(std140) uniform Hidden${i + 1} { vec4 w${i + 1}[${4 * g * G[i]}]; };`).join("\n");
  return `
uniform sampler2DArray learnedCodes;${m.arrays.learned_bounds ? "\nuniform sampler2DArray learnedBounds;" : ""}
layout(std140) uniform Decoder { vec4 decoder[${L.vec4s}]; };
${hiddenBlocks}
float decodeDisplay(float y) { float t = abs(y); return sign(y) * (t <= 0.04045 ? t / 12.92 : pow((t + 0.055) / 1.055, 2.4)); }
vec3 residual(ivec2 pixel${L.seeing ? ", float S" : ""}) {${L.seeing ? `
  float g = max(S, 0.0) / decoder[${L.unit}].x, root = sqrt(g);` : ""}
  vec3 c0 = texelFetch(learnedCodes, ivec3(pixel, 0), 0).rgb, c1 = texelFetch(learnedCodes, ivec3(pixel, 1), 0).rgb, c2 = texelFetch(learnedCodes, ivec3(pixel, 2), 0).rgb;
  vec4 z[3] = vec4[3](vec4(c0, c1.r), vec4(c1.gb, c2.rg), vec4(c2.b, 0.0, 0.0, 0.0));
  ${G.map((g, k) => `vec4 h${k}[${g}];`).join(" ")}
${G.map((g, k) => layer(k, k === 0 ? "z" : `h${k - 1}`, k === 0 ? 3 : G[k - 1])).join("\n")}
  vec3 y = decoder[${L.outBias}].xyz;
  for (int q = 0; q < ${G[last]}; q++) y += vec3(dot(decoder[${L.out} + q], h${last}[q]), dot(decoder[${L.out + G[last]} + q], h${last}[q]), dot(decoder[${L.out + 2 * G[last]} + q], h${last}[q]));
  vec3 r = clamp(decoder[${L.unit}].x * vec3(decodeDisplay(y.x), decodeDisplay(y.y), decodeDisplay(y.z)), -${FLOAT16_SAFE}, ${FLOAT16_SAFE});
  // float16, as Relighter keeps it${m.arrays.learned_bounds ? `, within the residual's bounds (PORTING.md 1.5c)
  r = vec3(unpackHalf2x16(packHalf2x16(r.xy)), unpackHalf2x16(packHalf2x16(vec2(r.z, 0.0))).x);
  return clamp(r, texelFetch(learnedBounds, ivec3(pixel, 0), 0).rgb, texelFetch(learnedBounds, ivec3(pixel, 1), 0).rgb);` : `
  return vec3(unpackHalf2x16(packHalf2x16(r.xy)), unpackHalf2x16(packHalf2x16(vec2(r.z, 0.0))).x);`}
}`;
}

function mainShader(m, source) {
  const colour = m.arrays.colour;
  const integer = colour && colour.dtype === "|u1";
  const take = m.channels === 3 ? ".rgb" : ".rrr";
  const tint = !colour ? "vec3(1.0)" : integer ? `vec3(texelFetch(colourMap, pixel, 0)${take}) * ${m.colour_step.toExponential(12)}` : `texelFetch(colourMap, pixel, 0)${take}`;
  // a decoder that sees the highlights gives the whole image, S its input: the tinted Gaussians are not added
  const seeing = m.residual.kind === "learned" && Boolean(m.residual.sees_highlights);
  const value = seeing ? "residual(pixel, S)" : `residual(pixel) + ${m.channels === 3 ? "specularColour" : "vec3(specularColour.x)"} * tint * S`;
  return `${HEADER}
layout(std140) uniform Gaussians { vec4 gaussians[${2 * m.max_gaussians}]; };
uniform int count; uniform vec3 specularColour; uniform float scale;
${colour ? `uniform ${integer ? "highp usampler2D" : "sampler2D"} colourMap;` : ""}
${source}
out vec4 colour;
const float CUTOFF2 = ${(m.cutoff * m.cutoff).toFixed(8)};
const float TAU = ${Math.exp(-m.cutoff * m.cutoff / 2).toExponential(10)};
float encode(float v) { v = clamp(v, 0.0, 1.0); return v <= 0.0031308 ? 12.92 * v : 1.055 * pow(v, 1.0 / 2.4) - 0.055; }
void main() {
  ${pixelOf(m)}
  vec2 x = (vec2(pixel) + 0.5) / float(${m.height});
  float S = 0.0;
  for (int i = 0; i < count; i++) {
    vec4 g0 = gaussians[2 * i], g1 = gaussians[2 * i + 1];
    vec2 d = x - g0.xy;
    if (dot(d, d) > g1.w) continue;
    float u = g0.w * d.x + g1.x * d.y; float v = g0.w * d.y - g1.x * d.x;
    float d2 = u * u * g1.y + v * v * g1.z;
    if (d2 < CUTOFF2) S += g0.z * (exp(-0.5 * d2) - TAU);
  }
${seeing ? "" : `  vec3 tint = ${tint};\n`}  vec3 rgb = scale * max(${value}, 0.0);
  colour = vec4(encode(rgb.r), encode(rgb.g), encode(rgb.b), 1.0);
}`;
}

function decodeShader(m) {
  // one captured light's residual R_i(x), clipped to float16's range, into a texture layer (batching
  // several lights a pass with multiple render targets saved nothing on SwiftShader: its cost is per light)
  return `${HEADER}
${stackSource(m)}
out vec4 colour;
void main() {
  // texel (x, y) of the layer holds pixel (x, y): rows top first, as uploaded images
  ivec2 pixel = ivec2(gl_FragCoord.xy);
  colour = vec4(clamp(residual(pixel), -${FLOAT16_SAFE}, ${FLOAT16_SAFE}), 1.0);
}`;
}

// --- textures -----------------------------------------------------------------------------------

function textureFormat(gl, dtype, channels) {
  const i = channels - 1;
  const formats = {
    "|u1": [[gl.R8UI, gl.RG8UI, gl.RGB8UI, gl.RGBA8UI], true, gl.UNSIGNED_BYTE],
    "<u2": [[gl.R16UI, gl.RG16UI, gl.RGB16UI, gl.RGBA16UI], true, gl.UNSIGNED_SHORT],
    "<f2": [[gl.R16F, gl.RG16F, gl.RGB16F, gl.RGBA16F], false, gl.HALF_FLOAT],
    "<f4": [[gl.R32F, gl.RG32F, gl.RGB32F, gl.RGBA32F], false, gl.FLOAT],
  }[dtype];
  if (!formats) throw new Error(`no texture format for ${dtype}`);
  const [internal, integer, type] = formats;
  const format = integer ? [gl.RED_INTEGER, gl.RG_INTEGER, gl.RGB_INTEGER, gl.RGBA_INTEGER][i] : [gl.RED, gl.RG, gl.RGB, gl.RGBA][i];
  return { internal: internal[i], format, type };
}

// --- the viewer ---------------------------------------------------------------------------------

export class Viewer {
  static async load(canvas, manifestUrl, options = {}) {
    const response = await fetch(manifestUrl);
    if (!response.ok) throw new Error(`manifest.json: ${response.status} ${response.statusText}`);
    const manifest = checkManifest(await response.json());
    return new Viewer(canvas, manifest, await fetchArrays(manifestUrl, manifest), options);
  }

  static async fromEmbedded(canvas, embedded, options = {}) {
    // a --single-file page: the manifest and the arrays (base64) in the page itself
    const manifest = checkManifest(embedded.manifest), arrays = {};
    await Promise.all(Object.entries(manifest.arrays).map(async ([name, spec]) => {
      arrays[name] = typed(spec, await inflated(spec, await fromBase64(embedded.arrays[name])));
    }));
    return new Viewer(canvas, manifest, arrays, options);
  }

  constructor(canvas, manifest, arrays, { decode = "auto" } = {}) {
    // decode (low-rank fields): "load" each light's residual into a float16 layer once (decodeRest; until
    // a triangle's corners are, its frames decode the stack per pixel), "query" the stack every frame,
    // or "auto": load where the browser can render to float16 textures and the layers fit
    if (!["auto", "load", "query"].includes(decode)) throw new Error(`decode must be auto, load or query, got ${decode}`);
    this.manifest = manifest; this.arrays = arrays; this.method = "circular";
    this.specularColour = [1, 1, 1]; this.exposureStops = 0;
    canvas.width = manifest.width; canvas.height = manifest.height;
    const gl = canvas.getContext("webgl2", { preserveDrawingBuffer: true, premultipliedAlpha: false, antialias: false });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    const largest = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (manifest.width > largest || manifest.height > largest) {
      throw new Error(`the field is ${manifest.width}x${manifest.height}; this browser's textures hold at most ${largest} pixels a side: export a smaller field (fit --size)`);
    }
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    this.unit = 0; this.units = {}; this.blocks = {};
    const { width, height, channels } = manifest, kind = manifest.residual.kind, n = manifest.lights;
    for (const name of ["colour", "scale"]) if (arrays[name]) this.texture(name, false);
    if (kind === "lowrank") {
      for (const name of ["luminance", "chroma"]) {
        if (!manifest.residual[name]) continue;
        this.texture(`${name}_mean`, false);
        this.texture(`${name}_codes`, true);
      }
      this.factorsTexture = this.emptyTexture("factors");
      // decode each light once into a float16 layer when the browser can render to one, else per frame
      const layerBytes = width * height * (channels === 3 ? 8 : 2);
      const canDecode = gl.getExtension("EXT_color_buffer_float") && n <= gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS) && n * layerBytes <= DECODED_BYTES;
      const rbf = Boolean(manifest.residual.rbf_sigma);
      if (decode === "load" && rbf) throw new Error("this field's residual weighs every light (radial basis): images decoded once per light cannot serve it");
      if (decode === "load" && !canDecode) throw new Error("this browser cannot hold the decoded residual images (float16 render targets)");
      this.mode = canDecode && decode !== "query" && !rbf ? "decoded" : "stack";
    } else if (kind === "images") {
      if (n > gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS)) throw new Error(`this browser holds ${gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS)} images per texture, the field has ${n} lights`);
      this.texture("images", true, "residualImages");
      this.mode = "images";
    } else if (kind === "learned") {
      this.texture("learned_codes", true);
      if (arrays.learned_bounds) this.texture("learned_bounds", true);
      this.mode = "learned";
    } else {
      throw new Error(`unknown residual kind ${kind}`);
    }
    this.decoded = new Uint8Array(n);
    this.allLights = Array.from({ length: n }, (_, i) => i);
    if (this.mode !== "decoded") this.decoded.fill(1);
    // one program a way of drawing; a decoded field starts with "stack" and adds "layers" (prepareLayers)
    const way = this.mode === "decoded" ? "stack" : this.mode;
    const source = { images: layersSource, stack: stackSource, learned: learnedSource }[way](manifest);
    this.programs = { [way]: this.program(mainShader(manifest, source)) };
    this.gaussianBuffer = this.uniformBlock(this.programs[way], "Gaussians", new Float32Array(8 * manifest.max_gaussians));
    if (this.mode === "learned") this.uploadDecoder();
    this.checkErrors("loading the field");
  }

  // --- set-up -----------------------------------------------------------------------------------

  program(fragment) {
    const gl = this.gl;
    const compile = (type, source) => {
      const shader = gl.createShader(type); gl.shaderSource(shader, source); gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      return shader;
    };
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl.FRAGMENT_SHADER, fragment));
    gl.bindAttribLocation(program, 0, "corner");
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    gl.useProgram(program);
    for (const [uniform, unit] of Object.entries(this.units)) {
      const location = gl.getUniformLocation(program, uniform);
      if (location) gl.uniform1i(location, unit);
    }
    if (!this.triangle) {
      this.triangle = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, this.triangle);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    }
    program.uniforms = {};
    program.set = (name, kind, ...values) => {
      if (!(name in program.uniforms)) program.uniforms[name] = gl.getUniformLocation(program, name);
      if (program.uniforms[name]) gl[`uniform${kind}`](program.uniforms[name], ...values);
    };
    return program;
  }

  checkErrors(what) {
    const error = this.gl.getError();
    if (error === this.gl.OUT_OF_MEMORY) throw new Error(`${what}: the GPU is out of memory`);
    if (error !== this.gl.NO_ERROR) throw new Error(`${what}: WebGL error 0x${error.toString(16)}`);
  }

  nearest(target) {
    const gl = this.gl;
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(target, p, gl.NEAREST);
    for (const p of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T]) gl.texParameteri(target, p, gl.CLAMP_TO_EDGE);
  }

  texture(name, layered, uniform = undefined) {
    // an exported array as a texture: (H, W[, C]) -> 2D, (L, H, W[, C]) -> 2D array; channels last
    const gl = this.gl, spec = this.manifest.arrays[name], data = this.arrays[name];
    const { width, height } = this.manifest, shape = spec.shape;
    const lead = layered ? 1 : 0, channels = shape.length > lead + 2 ? shape[lead + 2] : 1;
    const { internal, format, type } = textureFormat(gl, spec.dtype, channels);
    const texture = gl.createTexture(), unit = this.unit++;
    this.units[uniform || camel(name)] = unit;
    gl.activeTexture(gl.TEXTURE0 + unit);
    const target = layered ? gl.TEXTURE_2D_ARRAY : gl.TEXTURE_2D;
    gl.bindTexture(target, texture);
    if (layered) gl.texImage3D(target, 0, internal, width, height, shape[0], 0, format, type, data);
    else gl.texImage2D(target, 0, internal, width, height, 0, format, type, data);
    this.nearest(target);
    return texture;
  }

  emptyTexture(uniform) {
    const gl = this.gl, texture = gl.createTexture(), unit = this.unit++;
    this.units[uniform] = unit;
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, texture);
    this.nearest(gl.TEXTURE_2D);
    return { texture, unit };
  }

  uniformBlock(program, name, values) {
    // program's uniform block name backed by a new buffer of values, or by the block's buffer already made
    const gl = this.gl, index = gl.getUniformBlockIndex(program, name);
    if (index === gl.INVALID_INDEX) throw new Error(`the shader has no uniform block ${name}`);
    if (gl.getActiveUniformBlockParameter(program, index, gl.UNIFORM_BLOCK_DATA_SIZE) > gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE)) {
      throw new Error(`${name} is larger than this browser's uniform blocks`);
    }
    if (!(name in this.blocks)) {
      const buffer = gl.createBuffer();
      gl.bindBuffer(gl.UNIFORM_BUFFER, buffer);
      gl.bufferData(gl.UNIFORM_BUFFER, values, gl.DYNAMIC_DRAW);
      gl.bindBufferBase(gl.UNIFORM_BUFFER, Object.keys(this.blocks).length, buffer);
      this.blocks[name] = { buffer, binding: Object.keys(this.blocks).length };
    }
    gl.uniformBlockBinding(program, index, this.blocks[name].binding);
    return this.blocks[name].buffer;
  }

  uploadDecoder() {
    // the learned residual's weights in std140 blocks (decoderLayout): rows of vec4, the direction's columns of w0
    // zeroed (the first bias takes them in per frame); where it sees the highlights, w0's last two columns a vec4 of
    // four units' sqrt(g) weights, then one of their g weights
    const a = this.arrays, L = decoderLayout(this.manifest), G = L.groups, last = G.length - 1, w0 = a.learned_w0;
    const decoder = new Float32Array(4 * L.vec4s);
    for (let i = 0; i < L.hidden[0]; i++) {
      for (let j = 0; j < 9; j++) decoder[i * 12 + j] = w0[i * L.columns + j];
      if (L.seeing) {
        const at = 4 * (L.highlights + 2 * Math.floor(i / 4)) + (i % 4);
        decoder[at] = w0[i * L.columns + 12]; decoder[at + 4] = w0[i * L.columns + 13];
      }
    }
    G.forEach((_, k) => decoder.set(a[`learned_b${k}`], 4 * L.biases[k]));
    decoder.set(a[`learned_w${last + 1}`], 4 * L.out); decoder.set(a[`learned_b${last + 1}`], 4 * L.outBias);
    decoder[4 * L.unit] = this.manifest.residual.unit;
    this.decoderValues = decoder;
    const program = this.programs.learned;
    this.uniformBlock(program, "Decoder", decoder);
    for (let k = 1; k <= last; k++) this.uniformBlock(program, `Hidden${k}`, new Float32Array(a[`learned_w${k}`]));
  }

  // --- per light and per frame --------------------------------------------------------------------

  stackFactors(weights, lights) {
    // the factors texture's values (a vec4 per group of four packed codes: coef_j * step_j of each item's
    // basis j, luminance then chroma Cb then Cr) and the constants; weights[k] of light lights[k]
    const m = this.manifest, a = this.arrays, values = [], terms = {};
    const plane = (name, keep) => {
      const stack = m.residual[name], rank = stack.rank, L = stack.bits === 8 ? 255 : 65535;
      const W = a[`${name}_weights`], R = a[`${name}_ranges`], MW = a[`${name}_mean_weights`];
      let mean = 0, constant = 0;
      const factor = new Float64Array(rank);
      for (let k = 0; k < lights.length; k++) mean += weights[k] * MW[lights[k]];
      for (let j = 0; j < rank; j++) {
        let coef = 0;
        for (let k = 0; k < lights.length; k++) coef += weights[k] * W[lights[k] * rank + j];
        factor[j] = coef * ((R[2 * j + 1] - R[2 * j]) / L);
        constant += coef * R[2 * j];
      }
      for (let i = 0; i < 4 * stack.groups; i++) {
        const j = Math.floor(i / stack.planes), p = i % stack.planes;
        values.push(j < rank && (keep < 0 || p === keep) ? factor[j] : 0);
      }
      terms[name] = { mean, constant };
    };
    plane("luminance", -1);
    if (m.residual.chroma && m.channels === 3) { plane("chroma", 0); plane("chroma", 1); }
    return { values: new Float32Array(values), terms };
  }

  setStack(program, weights, lights) {
    const gl = this.gl, { values, terms } = this.stackFactors(weights, lights);
    gl.activeTexture(gl.TEXTURE0 + this.factorsTexture.unit);
    gl.bindTexture(gl.TEXTURE_2D, this.factorsTexture.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, values.length / 4, 1, 0, gl.RGBA, gl.FLOAT, values);
    for (const [name, term] of Object.entries(terms)) {
      program.set(`${name}Weight`, "1f", term.mean);
      program.set(`${name}Constant`, "1f", term.constant);
    }
  }

  prepareLayers() {
    // the float16 layers of the decoded residuals, the decoder, and the program that blends three layers
    if (this.layers) return;
    const gl = this.gl, m = this.manifest;
    this.layers = gl.createTexture();
    this.units.residualImages = this.unit++;
    gl.activeTexture(gl.TEXTURE0 + this.units.residualImages);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.layers);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, m.channels === 3 ? gl.RGBA16F : gl.R16F, m.width, m.height, m.lights);
    this.nearest(gl.TEXTURE_2D_ARRAY);
    this.checkErrors("making the decoded layers");
    this.framebuffer = gl.createFramebuffer();
    this.decoder = this.program(decodeShader(m));
    this.programs.layers = this.program(mainShader(m, layersSource(m)));
    this.uniformBlock(this.programs.layers, "Gaussians", this.gaussianBuffer);
  }

  decodeLight(light) {
    // light's residual image R_i into its float16 layer; on failure no layers: frames decode per pixel
    const gl = this.gl, { width, height } = this.manifest;
    try {
      this.prepareLayers();
      gl.useProgram(this.decoder);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.framebuffer);
      gl.viewport(0, 0, width, height);
      this.setStack(this.decoder, [1], [light]);
      gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, this.layers, 0, light);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error("this browser cannot render into float16 textures");
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      this.decoded[light] = 1;
    } catch (error) {
      this.layers = null; this.decoded.fill(0); this.mode = "stack"; this.decodeError = error.message;
      throw error;
    } finally {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    }
  }


  defaultDirection() {
    // the first light, as view's: the centroid of the triangle that (0.3, 0.4, 1) falls in (every corner weighs the
    // same)
    const face = locate(this.manifest, this.arrays, [0.3, 0.4, 1]).face, d = [0, 0, 0];
    for (let k = 0; k < 3; k++) for (let i = 0; i < 3; i++) d[i] += this.arrays.directions[3 * this.arrays.faces[3 * face + k] + i];
    const length = Math.hypot(...d);
    return d.map((v) => v / length);
  }

  nextToDecode() {
    // the light not decoded yet that is nearest the current light (-1: none left)
    const d = this.location ? this.location.located : [0, 0, 1], a = this.arrays.directions;
    let best = -1, closest = -Infinity;
    for (let light = 0; light < this.decoded.length; light++) {
      const near = a[3 * light] * d[0] + a[3 * light + 1] * d[1] + a[3 * light + 2] * d[2];
      if (!this.decoded[light] && near > closest) { closest = near; best = light; }
    }
    return best;
  }

  decodedCount() { return this.decoded.reduce((a, b) => a + b, 0); }

  decodeRest(onProgress = () => {}) {
    // decode the lights not decoded yet, one at a time: the next is queued only when the GPU has
    // finished the last (a fence), so that a frame asked for meanwhile waits for one decode at most;
    // resolves when all are, or when decoding failed (decodeError says why; frames then decode per pixel)
    const gl = this.gl;
    return new Promise((resolve) => {
      const step = () => {
        const light = this.mode === "decoded" ? this.nextToDecode() : -1;
        onProgress(this.decodedCount(), this.manifest.lights);
        if (light < 0) { resolve(); return; }
        try { this.decodeLight(light); } catch { resolve(); return; }
        const fence = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
        gl.flush();
        const done = () => {
          if (gl.clientWaitSync(fence, 0, 0) === gl.TIMEOUT_EXPIRED) { setTimeout(done, 1); return; }
          gl.deleteSync(fence);
          setTimeout(step, 0);
        };
        done();
      };
      setTimeout(step, 0);  // after the frame being drawn
    });
  }

  setLight(direction, method = this.method) {
    // relight for direction (x, y, z; any length) with method circular, straight or alpha; returns ms
    const started = performance.now();
    const gl = this.gl, m = this.manifest;
    if (!["circular", "straight", "alpha"].includes(method)) throw new Error(`method must be circular, straight or alpha, got ${method}`);
    if (method === "alpha" && this.mode === "learned") throw new Error("the alpha blend needs per-light residual images; a learned residual has none");
    this.method = method;
    this.location = locate(m, this.arrays, direction);
    const corners = [0, 1, 2].map((k) => this.arrays.faces[this.location.face * 3 + k]), w = this.location.weights;
    // the decoded layers once every corner that weighs is decoded (decodeRest), the stack per pixel before
    const layered = this.layers && corners.every((light, k) => w[k] <= 0 || this.decoded[light]);
    this.drawnWith = this.mode === "decoded" ? (layered ? "layers" : "stack") : this.mode;
    const program = this.programs[this.drawnWith];
    gl.useProgram(program);
    const moved = movedGaussians(m, this.arrays, this.location, method);
    gl.bindBuffer(gl.UNIFORM_BUFFER, this.gaussianBuffer);
    gl.bufferSubData(gl.UNIFORM_BUFFER, 0, moved);
    program.set("count", "1i", moved.length / 8);
    if (this.drawnWith === "layers" || this.drawnWith === "images") {
      program.set("corners", "3i", ...corners);
      program.set("weights", "3f", ...w);
    } else if (this.drawnWith === "stack" && m.residual.rbf_sigma && method !== "alpha") {
      this.setStack(program, rbfWeights(m, this.arrays, this.location.located), this.allLights);
    } else if (this.drawnWith === "stack") {
      this.setStack(program, w, corners);
    } else {
      const d = this.location.located, v = this.decoderValues, w0 = this.arrays.learned_w0, b0 = this.arrays.learned_b0;
      const L = decoderLayout(m), first = 4 * L.biases[0], c = L.columns;
      for (let i = 0; i < L.hidden[0]; i++) v[first + i] = b0[i] + w0[i * c + 9] * d[0] + w0[i * c + 10] * d[1] + w0[i * c + 11] * d[2];
      gl.bindBuffer(gl.UNIFORM_BUFFER, this.blocks.Decoder.buffer);
      gl.bufferSubData(gl.UNIFORM_BUFFER, first * 4, v.subarray(first, first + L.hidden[0]));
    }
    program.set("specularColour", "3f", ...this.specularColour);
    program.set("scale", "1f", Math.pow(2, this.exposureStops) / m.exposure);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, m.width, m.height);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    return performance.now() - started;
  }

  pixels() {
    // the canvas as 8-bit RGBA, top row first
    const gl = this.gl, { width, height } = this.manifest, raw = new Uint8Array(width * height * 4);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, raw);
    const out = new Uint8Array(raw.length), row = width * 4;
    for (let y = 0; y < height; y++) out.set(raw.subarray((height - 1 - y) * row, (height - y) * row), y * row);
    return out;
  }
}

function camel(name) {
  // the sampler of an exported array: luminance_codes -> luminanceCodes; colour, scale -> colourMap, scaleMap
  return { colour: "colourMap", scale: "scaleMap" }[name] || name.replace(/_(.)/g, (_, c) => c.toUpperCase());
}
