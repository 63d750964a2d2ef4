// warp-highlights web viewer: relights an exported field as Relighter does (warp_highlights/web/PORTING.md).
// The light is located and the Gaussians are moved on the CPU (float64); the fragment shader draws
// them, decodes the low-rank residual and writes sRGB.

const TYPES = { "<f8": Float64Array, "<f4": Float32Array, "<i4": Int32Array, "|u1": Uint8Array, "<u2": Uint16Array };

async function fetchArrays(base, manifest) {
  const arrays = {};
  await Promise.all(Object.entries(manifest.arrays).map(async ([name, spec]) => {
    const response = await fetch(new URL(spec.file, base));
    if (!response.ok) throw new Error(`${spec.file}: ${response.status} ${response.statusText}`);
    const Type = TYPES[spec.dtype];
    if (!Type) throw new Error(`${spec.file}: unsupported dtype ${spec.dtype}`);
    arrays[name] = new Type(await response.arrayBuffer());
  }));
  return arrays;
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

export function movedGaussians(m, a, location, method) {
  // the Gaussians of the query, 8 floats each: mu.x, mu.y, peak, cos, sin, 1/(sx^2+eps), 1/(sy^2+eps), 0
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
      if (!a.moving[A * N + p]) {
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
      out.push(mu[0], mu[1], peak, Math.cos(theta), Math.sin(theta), 1 / (sx * sx + m.sigma_eps), 1 / (sy * sy + m.sigma_eps), 0);
    }
  }
  return new Float32Array(out);
}

const VERTEX = `#version 300 es
in vec2 corner; void main() { gl_Position = vec4(corner, 0.0, 1.0); }`;

function fragmentShader(m) {
  const chroma = m.stacks.chroma !== undefined && m.channels === 3;
  return `#version 300 es
precision highp float; precision highp int; precision highp usampler2DArray; precision highp sampler2DArray;
uniform sampler2D gaussians; uniform int count;
uniform sampler2DArray planes; uniform sampler2D factors;
uniform usampler2DArray lumaCodes; uniform int lumaLayers; uniform float lumaMean; uniform float lumaConst;
${chroma ? "uniform usampler2DArray chromaCodes; uniform int chromaRank; uniform float chromaMean; uniform vec2 chromaConst;" : ""}
uniform vec3 specularColour; uniform float scale;
out vec4 colour;
const float CUTOFF2 = ${(m.cutoff * m.cutoff).toFixed(8)};
const float TAU = ${Math.exp(-m.cutoff * m.cutoff / 2).toExponential(10)};
float encode(float v) { v = clamp(v, 0.0, 1.0); return v <= 0.0031308 ? 12.92 * v : 1.055 * pow(v, 1.0 / 2.4) - 0.055; }
void main() {
  ivec2 pixel = ivec2(int(gl_FragCoord.x), ${m.height} - 1 - int(gl_FragCoord.y));
  vec2 x = (vec2(pixel) + 0.5) / float(${m.height});
  float S = 0.0;
  for (int i = 0; i < count; i++) {
    vec4 g0 = texelFetch(gaussians, ivec2(2 * i, 0), 0), g1 = texelFetch(gaussians, ivec2(2 * i + 1, 0), 0);
    vec2 d = x - g0.xy; float u = g0.w * d.x + g1.x * d.y; float v = g0.w * d.y - g1.x * d.x;
    float d2 = u * u * g1.y + v * v * g1.z;
    if (d2 < CUTOFF2) S += g0.z * (exp(-0.5 * d2) - TAU);
  }
  float s = texelFetch(planes, ivec3(pixel, 0), 0).r;
  float Y = lumaMean * texelFetch(planes, ivec3(pixel, ${m.stacks.luminance.mean_layer}), 0).r + lumaConst;
  for (int j = 0; j < lumaLayers; j++) Y += texelFetch(factors, ivec2(j, 0), 0).r * float(texelFetch(lumaCodes, ivec3(pixel, j), 0).r);
  Y *= s;
  vec3 rgb = vec3(Y);
${chroma ? `  vec2 C = chromaMean * vec2(texelFetch(planes, ivec3(pixel, ${m.stacks.chroma.mean_layer}), 0).r, texelFetch(planes, ivec3(pixel, ${m.stacks.chroma.mean_layer + 1}), 0).r) + chromaConst;
  for (int j = 0; j < chromaRank; j++) {
    float f = texelFetch(factors, ivec2(lumaLayers + j, 0), 0).r;
    C += f * vec2(float(texelFetch(chromaCodes, ivec3(pixel, 2 * j), 0).r), float(texelFetch(chromaCodes, ivec3(pixel, 2 * j + 1), 0).r));
  }
  C *= s;
  rgb = vec3(Y + C.y, Y - (0.2126 * C.y + 0.0722 * C.x) / 0.7152, Y + C.x);` : ""}
  vec3 tint = ${m.channels === 3 ? "vec3(texelFetch(planes, ivec3(pixel, 1), 0).r, texelFetch(planes, ivec3(pixel, 2), 0).r, texelFetch(planes, ivec3(pixel, 3), 0).r)" : "vec3(texelFetch(planes, ivec3(pixel, 1), 0).r)"};
  rgb = scale * max(rgb + specularColour * tint * S, 0.0);
  colour = vec4(encode(rgb.r), encode(rgb.g), encode(rgb.b), 1.0);
}`;
}

export class Viewer {
  static async load(canvas, manifestUrl) {
    const response = await fetch(manifestUrl);
    if (!response.ok) throw new Error(`manifest.json: ${response.status} ${response.statusText}`);
    const manifest = await response.json();
    if (manifest.format !== "warp-highlights web viewer" || manifest.version !== 1) throw new Error("manifest.json is not a warp-highlights viewer of version 1");
    return new Viewer(canvas, manifest, await fetchArrays(manifestUrl, manifest));
  }

  constructor(canvas, manifest, arrays) {
    this.manifest = manifest; this.arrays = arrays; this.method = "circular"; this.specularColour = [1, 1, 1];
    canvas.width = manifest.width; canvas.height = manifest.height;
    const gl = canvas.getContext("webgl2", { preserveDrawingBuffer: true, premultipliedAlpha: false, antialias: false });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    const compile = (type, source) => {
      const shader = gl.createShader(type); gl.shaderSource(shader, source); gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      return shader;
    };
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl.FRAGMENT_SHADER, fragmentShader(manifest)));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    gl.useProgram(program);
    this.program = program;
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
    const corner = gl.getAttribLocation(program, "corner");
    gl.enableVertexAttribArray(corner); gl.vertexAttribPointer(corner, 2, gl.FLOAT, false, 0, 0);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    const { width, height } = manifest;
    const layers = (name) => manifest.arrays[name].shape[0];
    this.unit = 0;
    this.bindArray("planes", gl.R32F, gl.RED, gl.FLOAT, arrays.planes, width, height, layers("planes"));
    for (const name of ["luminance", "chroma"]) {
      const stack = manifest.stacks[name];
      if (!stack) continue;
      const codes = arrays[`${name}_codes`], count = Math.max(layers(`${name}_codes`), 1);
      const data = codes.length ? codes : (stack.bits === 8 ? new Uint8Array(width * height) : new Uint16Array(width * height));
      this.bindArray(name === "luminance" ? "lumaCodes" : "chromaCodes", stack.bits === 8 ? gl.R8UI : gl.R16UI, gl.RED_INTEGER,
                     stack.bits === 8 ? gl.UNSIGNED_BYTE : gl.UNSIGNED_SHORT, data, width, height, count);
    }
    this.factorsTexture = this.texture2d("factors");
    this.gaussiansTexture = this.texture2d("gaussians");
    gl.uniform1f(gl.getUniformLocation(program, "scale"), 1 / manifest.exposure);
  }

  bindArray(uniform, internal, format, type, data, width, height, depth) {
    const gl = this.gl, texture = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + this.unit);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, texture);
    gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, width, height, depth, 0, format, type, data);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
    gl.uniform1i(gl.getUniformLocation(this.program, uniform), this.unit++);
  }

  texture2d(uniform) {
    const gl = this.gl, texture = gl.createTexture(), unit = this.unit++;
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, texture);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    gl.uniform1i(gl.getUniformLocation(this.program, uniform), unit);
    return { texture, unit };
  }

  upload(target, data, width) {
    const gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + target.unit);
    gl.bindTexture(gl.TEXTURE_2D, target.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, data.internal, width, 1, 0, data.format, gl.FLOAT, data.values);
  }

  stackTerms(name, weights) {
    // per-layer factors coef_j * step_j, the constant sum_j coef_j * low_j and the mean's weight m
    const m = this.manifest, a = this.arrays, stack = m.stacks[name], face = this.location.face;
    const V = [0, 1, 2].map((k) => a.faces[face * 3 + k]);
    const rank = stack.rank, L = stack.bits === 8 ? 255 : 65535;
    const factors = [];
    let mean = 0, constant = 0;
    for (let k = 0; k < 3; k++) mean += weights[k] * a[`${name}_mean_weights`][V[k]];
    for (let j = 0; j < rank; j++) {
      let coef = 0;
      for (let k = 0; k < 3; k++) coef += weights[k] * a[`${name}_weights`][V[k] * rank + j];
      const low = a[`${name}_ranges`][2 * j], high = a[`${name}_ranges`][2 * j + 1];
      factors.push(coef * ((high - low) / L));
      constant += coef * low;
    }
    return { factors, constant, mean };
  }

  setLight(direction, method = this.method) {
    const started = performance.now();
    const gl = this.gl, m = this.manifest;
    this.method = method;
    this.location = locate(m, this.arrays, direction);
    const moved = method === "alpha" ? new Float32Array(0) : movedGaussians(m, this.arrays, this.location, method);
    const count = moved.length / 8;
    this.upload(this.gaussiansTexture, { internal: gl.RGBA32F, format: gl.RGBA, values: count ? moved : new Float32Array(8) }, Math.max(2 * count, 2));
    gl.uniform1i(gl.getUniformLocation(this.program, "count"), count);
    const w = this.location.weights;
    const luma = this.stackTerms("luminance", w);
    let factors = luma.factors;
    gl.uniform1i(gl.getUniformLocation(this.program, "lumaLayers"), m.stacks.luminance.rank);
    gl.uniform1f(gl.getUniformLocation(this.program, "lumaMean"), luma.mean);
    gl.uniform1f(gl.getUniformLocation(this.program, "lumaConst"), luma.constant);
    if (m.stacks.chroma && m.channels === 3) {
      const chroma = this.stackTerms("chroma", w);
      factors = factors.concat(chroma.factors);
      gl.uniform1i(gl.getUniformLocation(this.program, "chromaRank"), m.stacks.chroma.rank);
      gl.uniform1f(gl.getUniformLocation(this.program, "chromaMean"), chroma.mean);
      gl.uniform2f(gl.getUniformLocation(this.program, "chromaConst"), chroma.constant, chroma.constant);
    }
    this.upload(this.factorsTexture, { internal: gl.R32F, format: gl.RED, values: new Float32Array(factors.length ? factors : [0]) }, Math.max(factors.length, 1));
    gl.uniform3f(gl.getUniformLocation(this.program, "specularColour"), ...this.specularColour);
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
