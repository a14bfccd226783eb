// The sky behind the model (render/sky.py, sky.glsl): one full-screen triangle at the far plane,
// each pixel coloured by its view ray's world elevation from the sky's bins. The desktop draws
// it first without depth; here it is drawn last with the depth test (LEQUAL, no depth writes), so
// only pixels the model left empty run it: the same picture for fewer fragments.

import {glMat, worldFromPixel} from './camera.js';
import {uniforms} from './model.js';

export class SkyPass {
  // sky: {colours: [[r, g, b], …] in [0, 1], elevation_deg: [low, high]}
  constructor(gl, program, sky) {
    this.gl = gl;
    this.program = program;
    this.sky = sky;
    this.bins = sky.colours.length;
    const rgba = new Float32Array(this.bins * 4);
    sky.colours.forEach((c, i) => rgba.set([c[0], c[1], c[2], 1], i * 4));
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, this.bins, 1);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, this.bins, 1, gl.RGBA, gl.FLOAT, rgba);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.vao = gl.createVertexArray();
  }

  // Draw the sky seen by the camera {R, K} into the viewport (height h pixels) where the depth test lets it.
  draw(cam, h) {
    const gl = this.gl, [lo, hi] = this.sky.elevation_deg;
    gl.useProgram(this.program);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    uniforms(gl, this.program, {
      u_world_from_pixel: ['m3', glMat(worldFromPixel(cam))], u_height: ['1f', h],
      u_elevation: ['2f', lo * Math.PI / 180, hi * Math.PI / 180], u_bins: ['1i', this.bins], u_sky: ['1i', 0]});
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
  }
}
