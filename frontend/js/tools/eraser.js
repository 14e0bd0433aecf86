// Eraser: the brush with value 0 (unpainted). On the colour canvas this has the effect of
// 'destination-out' compositing -- erased pixels become fully transparent and the photo shows
// through -- but it is applied to the id buffer first (then recoloured), so no partially
// transparent, anti-aliased edge pixels can leave ambiguous ids behind.

import { BrushTool } from "./brush.js";

export class EraserTool extends BrushTool {
  constructor(editor) {
    super(editor);
    this.name = "eraser";
    this.label = "Eraser";
    this.key = "e";
  }
  get value() {
    return 0;
  }
}
