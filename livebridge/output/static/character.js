// livebridge render client: the 2D character view (flip-book compositing of CR states, CoArt).
// The samples arrive once (premultiplied RGBA layers per region, cross-fade weights); each frame brings
// only the CR states, and the page composites as livebridge/character/composite.py does.
// Wire format: see livebridge/character/live.py.
(() => {  // its own scope: app.js shares the page's globals
"use strict";

  const lbc = {              // state, also read by the browser test
    ready: false, framesReceived: 0, seq: -1, drawnSeq: -1, init: null, error: null,
  };
  window.livebridgeCharacter = lbc;

  let character = null;      // {width, height, neutral: Float32Array RGB, regions: [...]}

  function loadSamples(buffer) {
    const [kind, width, height, n] = new Uint32Array(buffer, 0, 4);
    if (kind !== 3 || !lbc.init || n !== lbc.init.regions.length) throw new Error("unexpected character samples");
    let offset = 16;
    const bytes = (count) => { const a = new Uint8Array(buffer, offset, count); offset += count; return a; };
    const rgba = bytes(width * height * 4), neutral = new Float32Array(width * height * 3);
    for (let p = 0; p < width * height; p++) for (let c = 0; c < 3; c++) neutral[3 * p + c] = rgba[4 * p + c] / 255;
    const regions = lbc.init.regions.map((info) => {
      const [x, y, w, h] = info.rect, nSamples = info.counts.reduce((a, b) => a + b, 0);
      const layers = Float32Array.from(bytes(nSamples * w * h * 4), (v) => v / 255);
      const nFades = info.fade_regions.length, fadeBytes = nFades * w * h;
      const fades = Float32Array.from(bytes(fadeBytes), (v) => v / 255);
      offset += (4 - (fadeBytes % 4)) % 4;
      const first = []; let k = 0; for (const count of info.counts) { first.push(k); k += count; }
      return { x, y, w, h, counts: info.counts, first, layers, fades, fadeRegions: info.fade_regions };
    });
    character = { width, height, neutral, regions, out: new Float32Array(width * height * 3) };
    const canvas = document.getElementById("character");
    canvas.width = width; canvas.height = height;
    document.getElementById("character-view").hidden = false;
    character.image = canvas.getContext("2d").createImageData(width, height);
    lbc.ready = true;
    draw(new Int32Array(n).fill(-1), new Float32Array(n));
  }

  function blendRegion(out, W, region, lower, wLo, upper, wHi, fadeOn) {
    const { x, y, w, h, layers, fades } = region, size = w * h;
    for (let i = 0; i < h; i++) for (let j = 0; j < w; j++) {
      const p = i * w + j;
      const aLo = lower < 0 ? 0 : layers[(lower * size + p) * 4 + 3], aHi = layers[(upper * size + p) * 4 + 3];
      const covered = wLo * aLo + wHi * aHi;
      if (covered === 0) continue;
      let fade = 1;
      for (let f = 0; f < fadeOn.length; f++) if (fadeOn[f]) fade *= fades[f * size + p];
      const keep = 1 - fade * covered, o = ((y + i) * W + x + j) * 3;
      for (let c = 0; c < 3; c++) {
        const cLo = lower < 0 ? 0 : layers[(lower * size + p) * 4 + c];
        out[o + c] = out[o + c] * keep + fade * (wLo * cLo + wHi * layers[(upper * size + p) * 4 + c]);
      }
    }
  }

  function draw(muscle, level) {
    const { width, height, neutral, regions, out, image } = character;
    out.set(neutral);
    const active = regions.map((_, r) => muscle[r] >= 0 && level[r] > 0);
    regions.forEach((region, r) => {
      if (!active[r]) return;
      const m = muscle[r], count = region.counts[m];
      const t = Math.min(Math.max(level[r], 0), 1) * count, lower = Math.min(Math.floor(t), count - 1);
      const fraction = t - lower, upper = region.first[m] + lower;   // layer of state lower + 1
      blendRegion(out, width, region, lower > 0 ? upper - 1 : -1, 1 - fraction, upper, fraction,
        region.fadeRegions.map((q) => active[q]));
    });
    const data = image.data;
    for (let p = 0; p < width * height; p++) {
      data[4 * p] = out[3 * p] * 255; data[4 * p + 1] = out[3 * p + 1] * 255; data[4 * p + 2] = out[3 * p + 2] * 255;
      data[4 * p + 3] = 255;
    }
    document.getElementById("character").getContext("2d").putImageData(image, 0, 0);
  }

  let pending = null, drawRequested = false;
  function onStates(buffer) {
    const [, seq, n] = new Uint32Array(buffer, 0, 3);
    pending = { seq, muscle: new Int32Array(buffer, 12, n), level: new Float32Array(buffer, 12 + 4 * n, n) };
    lbc.seq = seq; lbc.framesReceived++;
    if (drawRequested) return;
    drawRequested = true;
    requestAnimationFrame(() => {
      drawRequested = false;
      if (!character || !pending) return;
      draw(pending.muscle, pending.level);
      lbc.drawnSeq = pending.seq;
    });
  }

  lbc.onInit = (message) => { lbc.init = message; };
  lbc.onBinary = (kind, buffer) => {
    try {
      if (kind === 3) loadSamples(buffer);
      else if (kind === 4 && character) onStates(buffer);
    } catch (error) { lbc.error = String(error); console.error(error); }
  };
})();
