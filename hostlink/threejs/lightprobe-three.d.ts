// Type declarations for lightprobe-three.js (see its header comment for the behaviour).
import type { DirectionalLight, EventDispatcher, Group, LightProbe, Scene, Texture, WebGLRenderer } from "three";

/** The SH body of GET /api/v1/sh?convention=threejs (and the stream's "sh" messages). */
export interface ProbeSH {
  version: 1;
  kind: "sh";
  probe: string;
  frame: number;
  /** wall-clock seconds when the set was published */
  timestamp: number;
  /** wall-clock seconds, the middle of the exposure of the newest frame (absent for maps not from a camera) */
  captured?: number;
  unit: "relative" | "nit" | string;
  convention: "threejs";
  order: 2;
  /** 9 x [r, g, b]: radiance coefficients of all light */
  coefficients: number[][];
  /** 9 x [r, g, b]: without the primary light */
  ambient_coefficients: number[][];
  primary_light: { direction: [number, number, number]; rgb: [number, number, number]; solid_angle: number } | null;
  stale?: boolean;
  pose?: { rotation: number[][]; position: [number, number, number] };
}

export interface ProbeOptions {
  /** the probe's token (lightprobe token): the cube map needs it */
  token?: string;
  /** for the PMREM of the environment */
  renderer?: WebGLRenderer | null;
  /** the lights are added to it; its environment is kept up to date */
  scene?: Scene | null;
  /** keep scene.environment up to date (default true; needs renderer, scene and token) */
  environment?: boolean;
  /** cube map face size requested (default 64) */
  cubeSize?: number;
  /** refetch the cube map when an SH coefficient moved by this fraction of the DC term (default 0.02) */
  cubeChange?: number;
  cubeMinIntervalMs?: number;
  /** scale on every light: a number, or a function of the SH body (auto exposure) */
  exposure?: number | ((sh: ProbeSH) => number);
  /** lighting with no frame for this long is stale (default 1500 ms) */
  staleAfterMs?: number;
  /** reconnect backoff [first, longest] in ms (default [250, 2000]) */
  reconnectMs?: [number, number];
  lightDistance?: number;
  /** rotate the lights (and scene.environmentRotation) by the probe's pose (default false) */
  applyPose?: boolean;
}

export type ProbeState = "connecting" | "live" | "reconnecting" | "closed";

export interface ProbeEventMap {
  update: { message: ProbeSH };
  stale: { stale: boolean };
  state: { state: ProbeState };
  environment: { texture: Texture; frame: number };
  error: { error: Error };
}

export class ProbeConnection extends EventDispatcher<ProbeEventMap> {
  constructor(url: string, options?: ProbeOptions);
  readonly options: Required<ProbeOptions>;
  /** holds lightProbe, light and light.target (added to options.scene) */
  readonly group: Group;
  readonly lightProbe: LightProbe;
  readonly light: DirectionalLight;
  environment: Texture | null;
  state: ProbeState;
  stale: boolean;
  frame: number;
  /** wall-clock seconds: when the light reached the probe's sensor */
  captured: number | null;
  timestamp: number | null;
  /** seconds: this machine's clock minus captured */
  readonly age: number | null;
  message: ProbeSH | null;
  updates: number;
  close(): void;
  dispose(): void;
}

export function connectProbe(url: string, options?: ProbeOptions): ProbeConnection;
export function parseCubeKTX2(buffer: ArrayBuffer): { size: number; faces: Uint16Array[] };
export function toThreeCubeFaces(size: number, faces: Uint16Array[]): Uint16Array[];
